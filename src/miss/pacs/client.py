"""QIDO-RS, WADO-RS and STOW-RS against one :class:`PacsServer`, through dicomweb-client.

What a PACS sends is untrusted, like an upload:

- every response body is counted as it arrives (a ``requests`` response hook wraps the
  stream before dicomweb-client reads it) and cut off past a cap, so an endless answer
  costs bounded memory;
- query answers are read into plain, length-capped strings; UIDs must look like UIDs;
- retrieved instances must belong to the study and series asked for and be written in
  a transfer syntax MISS decodes; they are written to files as they come and their
  pixels are decoded only later, by the confined reader (:mod:`miss.io.confined`).

Failures become :class:`~miss.errors.PacsError` (502) or
:class:`~miss.errors.PacsTimeout` (504) with a message that names the PACS and what to
check; the credentials never appear in one.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from miss.errors import (
    BadParameter,
    InputTooLarge,
    PacsError,
    PacsTimeout,
    UnsupportedFormat,
    WrongStudy,
)
from miss.pacs.server import PacsServer

#: Largest query answer (JSON) accepted, bytes.
MAX_QUERY_BYTES = 16 << 20
#: Most studies or series one query page may list.
MAX_PAGE = 200
#: A UID, matched whole (``fullmatch``: ``$`` would let a trailing newline through).
UID = re.compile(r"[0-9]+(\.[0-9]+)*")
#: Transfer syntaxes MISS decodes (pydicom with pylibjpeg): little and big endian,
#: JPEG 2000, JPEG lossless, JPEG-LS, RLE, JPEG baseline and extended.
DECODED: frozenset[str] = frozenset(
    (
        "1.2.840.10008.1.2",  # implicit VR little endian
        "1.2.840.10008.1.2.1",  # explicit VR little endian
        "1.2.840.10008.1.2.1.99",  # deflated explicit VR little endian
        "1.2.840.10008.1.2.2",  # explicit VR big endian
        "1.2.840.10008.1.2.4.90",  # JPEG 2000 lossless
        "1.2.840.10008.1.2.4.91",  # JPEG 2000
        "1.2.840.10008.1.2.4.70",  # JPEG lossless, first-order prediction
        "1.2.840.10008.1.2.4.57",  # JPEG lossless
        "1.2.840.10008.1.2.4.80",  # JPEG-LS lossless
        "1.2.840.10008.1.2.4.81",  # JPEG-LS near-lossless
        "1.2.840.10008.1.2.5",  # RLE lossless
        "1.2.840.10008.1.2.4.50",  # JPEG baseline
        "1.2.840.10008.1.2.4.51",  # JPEG extended
    )
)
#: What MISS asks a PACS to transcode to when it stores a series in another syntax.
EXPLICIT = "1.2.840.10008.1.2.1"
#: Modalities whose series hold no image to model, and what they are.
NOT_IMAGES: dict[str, str] = {
    "SR": "a structured report",
    "PR": "a presentation state",
    "KO": "a key-object selection",
    "DOC": "a document",
    "SEG": "a segmentation (import it with its image series)",
    "RTSTRUCT": "an RT structure set (import it with its image series)",
    "RTPLAN": "an RT plan",
    "RTDOSE": "an RT dose",
    "REG": "a registration",
    "M3D": "a 3-D model",
    "OT": "",
}
#: SOP classes that are not images although their series' modality may say CT or MR.
NON_IMAGE_SOP_PREFIXES = ("1.2.840.10008.5.1.4.1.1.88.", "1.2.840.10008.5.1.4.1.1.11.")


def check_uid(uid: str, what: str) -> str:
    """A DICOM UID as MISS accepts it from a client or a PACS (digits and dots, <= 64)."""
    if not isinstance(uid, str) or len(uid) > 64 or not UID.fullmatch(uid):
        raise BadParameter(f"{what} {str(uid)[:80]!r} is not a DICOM UID (digits and dots).")
    return uid


# ---------------------------------------------------------------- connecting


def _cap_hook(limit: int) -> Callable[..., Any]:
    """A response hook that makes ``iter_content`` (which ``.content`` uses too) raise
    :class:`InputTooLarge` once more than ``limit`` bytes came."""

    def hook(response: Any, *args: Any, **kwargs: Any) -> Any:
        original = response.iter_content

        def counted(*a: Any, **k: Any) -> Iterator[bytes]:
            total = 0
            for chunk in original(*a, **k):
                total += len(chunk)
                if total > limit:
                    response.close()
                    raise InputTooLarge(
                        f"the PACS sent more than {limit >> 20} MB for one answer (the "
                        "upload limit); import a smaller series or raise MISS_MAX_UPLOAD_MB."
                    )
                yield chunk

        response.iter_content = counted
        return response

    return hook


def _session() -> Any:
    import requests

    class Session(requests.Session):
        """dicomweb-client escapes QIDO-RS wildcards (``*`` as ``%2A``), which DICOM
        defines as wildcards anyway; some PACS (Orthanc 1.10) then match them literally.
        Sent as they are, every PACS reads them as wildcards."""

        # typeshed's url is str | bytes; dicomweb-client passes str
        def request(self, method: str, url: str, *args: Any, **kwargs: Any) -> Any:  # type: ignore[override]
            url = url.replace("%2A", "*").replace("%3F", "?")
            return super().request(method, url, *args, **kwargs)

    return Session()


def connect(server: PacsServer, max_bytes: int = MAX_QUERY_BYTES) -> Any:
    """A ``DICOMwebClient`` for ``server``: its credentials, its timeout, no retries
    (a job is retried as a whole), answers capped at ``max_bytes``."""
    from dicomweb_client import DICOMwebClient

    session = _session()
    credentials = server.credentials()
    if isinstance(credentials, tuple):
        session.auth = credentials
    elif credentials:
        session.headers["Authorization"] = f"Bearer {credentials}"
    session.hooks["response"].append(_cap_hook(max_bytes))
    client = DICOMwebClient(url=server.url, session=session, timeout=server.timeout)
    client.set_http_retry_params(retry=False)
    return client


@contextlib.contextmanager
def calling(server: PacsServer, what: str) -> Iterator[None]:
    """Turn what ``requests`` and dicomweb-client raise into messages that name the
    PACS, what MISS was doing and what to check."""
    import requests

    try:
        yield
    except (PacsError, InputTooLarge, BadParameter, UnsupportedFormat, WrongStudy):
        raise
    except requests.Timeout:
        raise PacsTimeout(
            f"{server.where} did not answer within {server.timeout:g} s while {what}; it "
            "may be busy: try again, or raise MISS_PACS_TIMEOUT."
        ) from None
    except requests.ConnectionError as exc:
        reason = _reason(exc)
        raise PacsError(
            f"cannot reach {server.where} while {what} ({reason}); check that the PACS is "
            "running and that MISS_PACS_URL names its DICOMweb root."
        ) from None
    except requests.HTTPError as exc:
        raise PacsError(_http_message(server, what, exc.response)) from None
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise PacsError(
            f"{server.where} sent an answer MISS cannot read while {what} "
            f"({type(exc).__name__}); check that MISS_PACS_URL is its DICOMweb root."
        ) from None
    except Exception as exc:
        from pydicom.errors import InvalidDicomError

        if not isinstance(exc, InvalidDicomError):
            raise
        raise PacsError(
            f"{server.where} sent a part that is not a DICOM file (no preamble and 'DICM') "
            f"while {what}; check the PACS's DICOMweb settings or ask its administrator."
        ) from None


def _reason(exc: Exception) -> str:
    text = str(exc)
    for known in ("Connection refused", "Name or service not known", "No route to host"):
        if known in text:
            return known.lower()
    return "no connection"


def _http_message(server: PacsServer, what: str, response: Any) -> str:
    code = getattr(response, "status_code", 0)
    if code == 401:
        return (
            f"{server.where} refused MISS's credentials (401) while {what}; check the "
            "file MISS_PACS_AUTH_FILE names (user:password or Bearer TOKEN)."
        )
    if code == 403:
        return (
            f"{server.where} refused (403 forbidden) while {what}: the account in "
            "MISS_PACS_AUTH_FILE may not do this there; ask the PACS's administrator."
        )
    if code == 404:
        return (
            f"{server.where} answered 404 while {what}: it has no such study or series, or "
            "MISS_PACS_URL is not its DICOMweb root (e.g. http://host:8042/dicom-web)."
        )
    said = ""
    with contextlib.suppress(Exception):
        said = _printable(response.text[:300])
    return f"{server.where} answered {code} while {what}" + (f": {said}" if said else ".")


def _printable(text: str) -> str:
    return "".join(c if c.isprintable() else " " for c in text).strip()


# ---------------------------------------------------------------- query answers


def _value(item: Mapping[str, Any], tag: str, limit: int = 200) -> str:
    """The first value of ``tag`` in a DICOM JSON item, as a capped printable string."""
    element = item.get(tag)
    if not isinstance(element, Mapping):
        return ""
    values = element.get("Value")
    if not isinstance(values, list) or not values:
        return ""
    first = values[0]
    if isinstance(first, Mapping):  # a person name
        first = first.get("Alphabetic", "")
    if not isinstance(first, str | int | float) or isinstance(first, bool):
        return ""
    return _printable(str(first))[:limit]


def _values(item: Mapping[str, Any], tag: str) -> list[str]:
    element = item.get(tag)
    values = element.get("Value") if isinstance(element, Mapping) else None
    if not isinstance(values, list):
        return []
    return [_printable(v)[:16] for v in values[:32] if isinstance(v, str)]


def _count(item: Mapping[str, Any], tag: str) -> int | None:
    text = _value(item, tag, 12)
    try:
        return max(0, int(float(text)))
    except ValueError:
        return None


def _uid_of(item: Mapping[str, Any], tag: str) -> str | None:
    uid = _value(item, tag, 80)
    return uid if uid and len(uid) <= 64 and UID.fullmatch(uid) else None


# ---------------------------------------------------------------- QIDO-RS

#: Search fields the API takes -> DICOM keyword.
FILTERS: dict[str, str] = {
    "patient_id": "PatientID",
    "patient_name": "PatientName",
    "accession": "AccessionNumber",
    "study_date": "StudyDate",
    "modality": "ModalitiesInStudy",
}
_DATE = re.compile(r"(\d{8})?(-(\d{8})?)?")  # whole: fullmatch


def search_filters(given: Mapping[str, str | None]) -> dict[str, str]:
    """The QIDO-RS filters for ``given`` (API names), checked: no control characters or
    backslashes (DICOM's value separator), dates as YYYYMMDD or a range, a name without
    a wildcard matched as a prefix, in capitals (as DICOM names are kept; "doe jane"
    becomes ``DOE?JANE*``)."""
    filters: dict[str, str] = {}
    for name, keyword in FILTERS.items():
        value = (given.get(name) or "").strip()
        if not value:
            continue
        if len(value) > 64 or "\\" in value or not value.isprintable():
            raise BadParameter(
                f"{name} must be at most 64 printable characters without a backslash."
            )
        if name == "study_date":
            value = value.replace("-", "") if len(value) == 10 else value
            if not _DATE.fullmatch(value) or value == "-":
                raise BadParameter(
                    f"study_date must be YYYYMMDD or a range YYYYMMDD-YYYYMMDD, got {value!r}."
                )
        if name == "patient_name" and "*" not in value and "?" not in value:
            value += "*"
        if name == "patient_name":  # names are kept in capitals; not every PACS ignores case
            # "?" stands for the "^" between name parts, which Orthanc 1.10 cannot match
            # once a client has escaped it (as dicomweb-client does)
            value = value.upper().replace(" ", "?").replace("^", "?")
        if name == "modality":
            value = value.upper()
        filters[keyword] = value
    return filters


@dataclass(frozen=True)
class Page:
    """One page of a query: the rows, where it started and whether more follow."""

    rows: list[dict[str, Any]]
    offset: int
    limit: int
    more: bool


def search_studies(
    server: PacsServer, filters: Mapping[str, str], offset: int = 0, limit: int = 25
) -> Page:
    """Studies matching ``filters`` (DICOM keywords, from :func:`search_filters`)."""
    if not 1 <= limit <= MAX_PAGE or offset < 0:
        raise BadParameter(f"limit must be 1..{MAX_PAGE} and offset >= 0.")
    client = connect(server)
    with calling(server, "searching for studies"):
        found = client.search_for_studies(
            search_filters=dict(filters),
            offset=offset,
            limit=limit + 1,
            fields=[
                "StudyDescription",
                "ModalitiesInStudy",
                "NumberOfStudyRelatedSeries",
                "NumberOfStudyRelatedInstances",
                "PatientBirthDate",
                "PatientSex",
            ],
        )
    studies = [_study(item) for item in found[: limit + 1] if isinstance(item, Mapping)]
    rows = [r for r in studies if r]
    return Page(rows[:limit], offset, limit, len(rows) > limit)


def _study(item: Mapping[str, Any]) -> dict[str, Any] | None:
    uid = _uid_of(item, "0020000D")
    if uid is None:
        return None
    return {
        "study": uid,
        "patient_id": _value(item, "00100020", 64),
        "patient_name": _value(item, "00100010").replace("^", " ").strip(),
        "birth_date": _value(item, "00100030", 8),
        "sex": _value(item, "00100040", 1),
        "study_date": _value(item, "00080020", 8),
        "accession": _value(item, "00080050", 16),
        "description": _value(item, "00081030", 64),
        "modalities": _values(item, "00080061"),
        "series_count": _count(item, "00201206"),
        "instances": _count(item, "00201208"),
    }


def search_series(server: PacsServer, study: str) -> list[dict[str, Any]]:
    """The series of ``study``, each with modality, description, number, instance count
    and whether MISS can model it (``importable``, else ``reason``)."""
    check_uid(study, "study")
    client = connect(server)
    with calling(server, "listing the study's series"):
        found = client.search_for_series(
            study_instance_uid=study,
            limit=1000,
            fields=["SeriesDescription", "SeriesNumber", "NumberOfSeriesRelatedInstances"],
        )
    series = [_series(item) for item in found[:1000] if isinstance(item, Mapping)]
    rows = [r for r in series if r]
    return sorted(rows, key=lambda r: (r["number"] is None, r["number"] or 0, r["description"]))


def _series(item: Mapping[str, Any]) -> dict[str, Any] | None:
    uid = _uid_of(item, "0020000E")
    if uid is None:
        return None
    modality = _value(item, "00080060", 16).upper()
    what = NOT_IMAGES.get(modality)
    importable = what is None
    number = _count(item, "00200011")
    return {
        "series": uid,
        "modality": modality,
        "description": _value(item, "0008103E", 64),
        "number": number,
        "instances": _count(item, "00201209"),
        "importable": importable,
        "segmentation": modality in ("SEG", "RTSTRUCT"),
        "reason": None if importable else f"{modality} series: {what or 'not an image series'}",
    }


def list_instances(
    server: PacsServer, study: str, series: str, max_instances: int
) -> list[tuple[str, str]]:
    """(SOP class, SOP instance UID) of each instance; refuses more than ``max_instances``
    and a series whose instances are all of non-image classes."""
    client = connect(server)
    with calling(server, "listing the series' instances"):
        found = client.search_for_instances(
            study_instance_uid=check_uid(study, "study"),
            series_instance_uid=check_uid(series, "series"),
            limit=max_instances + 1,
            fields=["SOPClassUID", "SOPInstanceUID"],
        )
    rows = [
        (_uid_of(i, "00080016"), _uid_of(i, "00080018")) for i in found if isinstance(i, Mapping)
    ]
    instances = [(c, s) for c, s in rows if c and s]
    if len(instances) > max_instances:
        raise InputTooLarge(
            f"the series has more than {max_instances} instances, more than MISS reads in one "
            "volume; pick a series with fewer slices."
        )
    if not instances:
        raise PacsError(
            f"{server.where} lists no instances in series {series} of study {study}; check "
            "that the series is complete on the PACS."
        )
    return instances


# ---------------------------------------------------------------- WADO-RS


def retrieve_series(
    server: PacsServer,
    study: str,
    series: str,
    folder: Path,
    max_bytes: int,
    expected: int,
    progress: Callable[[int], None] | None = None,
    images: bool = True,
) -> list[Path]:
    """Write each instance of the series to ``folder`` (``00001.dcm`` ...) as it arrives.

    Asked for as stored (``transfer-syntax=*``: no transcoding on the PACS, which some
    cannot do for JPEG 2000); an instance in a syntax MISS does not decode
    (:data:`DECODED`) makes it ask again for explicit VR little endian, transcoded by the
    PACS. The answer is capped at ``max_bytes``; each instance must name the study and
    series asked for. Pixel data is not decoded here. ``expected`` is the instance count
    QIDO-RS gave. ``images=False`` takes instances without pixels too (RT-STRUCT).
    """
    asked = (server, study, series, folder, max_bytes, expected)
    try:
        return _retrieve(*asked, "*", progress, images)
    except _NotDecoded:
        for path in folder.glob("*.dcm"):
            path.unlink()
        return _retrieve(*asked, EXPLICIT, progress, images)


class _NotDecoded(Exception):
    """An instance came in a transfer syntax MISS does not decode."""


def _retrieve(
    server: PacsServer,
    study: str,
    series: str,
    folder: Path,
    max_bytes: int,
    expected: int,
    syntax: str,
    progress: Callable[[int], None] | None,
    images: bool,
) -> list[Path]:
    from pydicom import dcmwrite

    client = connect(server, max_bytes)
    written: list[Path] = []
    with calling(server, "retrieving the series"):
        for ds in client.iter_series(study, series, media_types=(("application/dicom", syntax),)):
            _check_instance(server, ds, study, series, syntax, images)
            if len(written) >= expected:
                raise PacsError(
                    f"{server.where} sent more instances than it listed ({expected}) for "
                    f"series {series}; it may be changing: try again later."
                )
            path = folder / f"{len(written) + 1:05d}.dcm"
            dcmwrite(path, ds, enforce_file_format=True)
            written.append(path)
            if progress:
                progress(len(written))
    if not written:
        raise PacsError(f"{server.where} sent no instance of series {series}; try again.")
    return written


def _check_instance(
    server: PacsServer, ds: Any, study: str, series: str, asked: str, images: bool
) -> None:
    got = (str(ds.get("StudyInstanceUID", "")), str(ds.get("SeriesInstanceUID", "")))
    if got != (study, series):
        raise PacsError(
            f"{server.where} sent an instance of another study or series than the one asked "
            "for; nothing was imported. Report this to the PACS's administrator."
        )
    meta = getattr(ds, "file_meta", None)
    syntax = str(getattr(meta, "TransferSyntaxUID", "") or "")
    if syntax not in DECODED:
        if asked == "*":
            raise _NotDecoded(syntax)
        raise UnsupportedFormat(
            f"{server.where} sent transfer syntax {syntax or '(none)'}, which MISS does not "
            "decode; configure the PACS to transcode to explicit VR little endian."
        )
    sop_class = str(ds.get("SOPClassUID", ""))
    if images and (sop_class.startswith(NON_IMAGE_SOP_PREFIXES) or "PixelData" not in ds):
        raise UnsupportedFormat(
            "the series holds no images (a report, presentation state or document); pick an "
            "image series (CT, MR ...)."
        )


# ---------------------------------------------------------------- STOW-RS


def study_attributes(server: PacsServer, study: str) -> dict[str, str] | None:
    """The patient and study attributes (:data:`miss.pacs.stl.PATIENT_STUDY` keywords)
    of ``study`` as the PACS has them now; None when it has no such study."""
    found = _studies(server, study)
    return found[0] if found else None


def _studies(server: PacsServer, study: str) -> list[dict[str, str]]:
    """Each entry the PACS lists for the Study Instance UID ``study`` (one, or more where
    a PACS keeps a UID per patient, as Orthanc does), as :func:`study_attributes`."""
    from pydicom.datadict import tag_for_keyword

    from miss.pacs.stl import PATIENT_STUDY

    client = connect(server)
    with calling(server, "looking up the study"):
        found = client.search_for_studies(
            search_filters={"StudyInstanceUID": check_uid(study, "study")},
            fields=list(PATIENT_STUDY),
        )
    tags = {keyword: f"{tag_for_keyword(keyword):08X}" for keyword in PATIENT_STUDY}
    return [
        {keyword: _value(item, tag, 64) for keyword, tag in tags.items()}
        for item in found[:MAX_PAGE]
        if isinstance(item, Mapping) and _uid_of(item, "0020000D") in (None, study)
    ]


def check_study(
    server: PacsServer, study: str, series: str, patient_id: str, issuer: str = ""
) -> dict[str, str]:
    """Ask the PACS (QIDO-RS) that ``study`` is there, still has the patient
    ``patient_id`` (and ``issuer``, when both name one) and holds ``series`` (none:
    unchecked); its patient and study attributes. :class:`WrongStudy` (409) otherwise,
    with a message that names no patient."""
    found = _studies(server, study)
    if not found:
        raise WrongStudy(
            f"{server.where} has no study {study}; nothing was sent. Find the study with a "
            "PACS search (deleted or merged since the import? import the series again).",
            study,
        )
    if not all(_same_patient(held, patient_id, issuer) for held in found):
        raise WrongStudy(
            f"study {study} on {server.where} has another patient ID than the model's (the "
            "one recorded when its series was imported, or --patient-id); nothing was sent. "
            "Check the study's patient with a PACS search, or ask the PACS's administrator.",
            study,
        )
    if series and series not in {r["series"] for r in search_series(server, study)}:
        raise WrongStudy(
            f"study {study} on {server.where} does not hold the series {series} the model "
            "was made from (deleted or moved?); nothing was sent. Import it again from the PACS.",
            study,
        )
    return found[0]


def _same_patient(held: Mapping[str, str], patient_id: str, issuer: str) -> bool:
    """Whether a study entry names ``patient_id`` (and ``issuer``, where both name one)."""
    theirs = held.get("IssuerOfPatientID", "")
    same_issuer = not (issuer and theirs) or issuer == theirs
    return held.get("PatientID", "").strip() == patient_id.strip() and same_issuer


def study_origin(
    server: PacsServer, study: str, series: str | None, patient_id: str, issuer: str = ""
) -> Any:
    """Where a model sent from the command line belongs, checked (:func:`check_study`):
    the study's patient and study attributes as the PACS has them, and with ``series``
    (its source images) that series' frame of reference and images; without it a new
    frame of reference."""
    from pydicom.uid import generate_uid

    from miss.pacs.stl import Origin

    patient = check_study(server, study, series or "", patient_id, issuer)
    frame: str = generate_uid()
    sources: list[tuple[str, str]] = []
    if series:
        client = connect(server)
        with calling(server, "reading the series' metadata"):
            metadata = client.retrieve_series_metadata(study, check_uid(series, "series"))
        frames = {u for u in (_uid_of(m, "00200052") for m in metadata) if u is not None}
        frame = frames.pop() if len(frames) == 1 else frame
        pairs = [(_uid_of(m, "00080016"), _uid_of(m, "00080018")) for m in metadata]
        sources = [(c, i) for c, i in pairs if c and i]
    return Origin(study, series or "", frame, patient, sources)


def store(server: PacsServer, datasets: Sequence[Any], study: str) -> list[str]:
    """Send ``datasets`` (one new series) into ``study``; the SOP Instance UIDs stored.

    What the PACS says is checked against what it holds: a refusal, whole or of one
    instance, raises :class:`PacsError` with the PACS's reason, and so does an answer of
    success for instances a query then does not find (Orthanc's DICOMweb plugin 1.7
    reports instances its own filters dropped as stored)."""
    client = connect(server)
    with calling(server, "storing the model"):
        answer = client.store_instances(list(datasets), study_instance_uid=study)
    failed = answer.get("FailedSOPSequence") or []
    if failed:
        reasons = sorted({str(item.get("FailureReason", "?")) for item in failed})
        raise PacsError(
            f"{server.where} refused {len(failed)} of {len(datasets)} instance(s) (DICOM "
            f"failure reason {', '.join(reasons)}); ask its administrator whether it accepts "
            "Encapsulated STL (1.2.840.10008.5.1.4.1.1.104.3)."
        )
    sent = [str(ds.SOPInstanceUID) for ds in datasets]
    series = str(datasets[0].SeriesInstanceUID)
    with calling(server, "checking what it stored"):
        found = client.search_for_instances(
            study_instance_uid=study, series_instance_uid=series, fields=["SOPInstanceUID"]
        )
    held = {_uid_of(item, "00080018") for item in found if isinstance(item, Mapping)}
    stored = [uid for uid in sent if uid in held]
    if len(stored) != len(sent):
        raise PacsError(
            f"{server.where} holds {len(stored)} of the {len(sent)} instance(s) it was sent "
            "(it answered without a refusal, yet a query does not find them: a filter on the "
            "PACS may drop 3-D models); ask its administrator to accept Encapsulated STL "
            "(1.2.840.10008.5.1.4.1.1.104.3)."
        )
    return stored
