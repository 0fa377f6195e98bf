"""DICOM series reader: find the slices, group them by series, pick one, stack it.

A folder (searched recursively), a ``.zip`` of one, or a single file. Headers are read
first without pixels to group files by ``SeriesInstanceUID``; only the chosen series is
decoded (compressed transfer syntaxes through the pylibjpeg plug-ins). Stacking, slice
order, gantry tilt and uneven gaps are handled in :mod:`miss.io.dicom_stack`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from miss.deid import IDENTIFYING
from miss.errors import BadParameter, MissError, UnreadableVolume, UnsupportedFormat
from miss.io.common import (
    Streamed,
    checked_affine,
    make_volume,
    recorded_warnings,
    streamed_meta,
)

if TYPE_CHECKING:
    from pydicom.dataset import Dataset

    from miss.io.dicom_files import Entry
    from miss.types import Volume

# pydicom (0.3 s to load) and the modules built on it are imported by the functions that
# read: a volume in any other format, and ``sniff``, never load it.
EXTENSIONS = {".dcm", ".dicom", ".ima", ".zip"}
#: Identifying attributes go to ``Volume.patient``, apart from ``meta`` (see miss.deid).
PATIENT_TAGS = IDENTIFYING
#: Volume formats people drop into a folder next to (or instead of) DICOM slices.
OTHER_VOLUMES = ("*.nhdr", "*.nrrd", "*.mhd", "*.mha", "*.nii", "*.nii.gz")


@dataclass(frozen=True)
class Header:
    """A slice file's header (no pixels yet) and where to fetch the full file."""

    entry: Entry
    ds: Dataset


def sniff(path: Path, head: bytes) -> bool:
    """Folders, zips, ``.dcm``-like names, the ``DICM`` preamble, or a bare group-8 start."""
    if path.is_dir() or path.suffix.lower() in EXTENSIONS or head[:4] == b"PK\x03\x04":
        return True
    return head[128:132] == b"DICM" or head[:2] in (b"\x08\x00", b"\x02\x00")


def list_series(path: Path) -> list[dict[str, Any]]:
    """Describe every series found: [{"uid", "description", "modality", "slices", "dims"}]."""
    from miss.io.dicom_files import open_source

    with open_source(path) as entries:
        groups, _ = _grouped_headers(path, entries)
    return [_describe(uid, headers) for uid, headers in groups.items()]


def list_series_identity(path: Path) -> tuple[list[dict[str, Any]], dict[str, str]]:
    """:func:`list_series`, and the identifying attributes any file of any series holds
    (as ``Volume.patient`` gives them): what to cut out of the descriptions listed."""
    from miss.io.dicom_files import open_source

    with open_source(path) as entries:
        groups, _ = _grouped_headers(path, entries)
    listed = [_describe(uid, headers) for uid, headers in groups.items()]
    return listed, (_patient(groups, next(iter(groups))) if groups else {})


def read(path: Path, series: str | None) -> Volume:
    """Read one series as a ``Volume`` (the one with most slices unless ``series`` names a UID)."""
    from miss.io import dicom_stack
    from miss.io.dicom_files import open_source

    with open_source(path) as entries:
        groups, notes = _grouped_headers(path, entries)
        uid = _choose(path, groups, series)
        _refuse_multiframe(groups[uid])
        stack = dicom_stack.assemble(path, [(h.entry, h.ds) for h in groups[uid]])
    return make_volume(
        path,
        stack.data,
        stack.affine,
        "dicom",
        notes=notes + stack.notes,
        patient=_patient(groups, uid),
        **_series_meta(groups, uid, stack.rescale),
    )


def stream(path: Path, series: str | None = None) -> Streamed | None:
    """A folder's series as (X, Y) planes decoded one slice at a time (``miss ingest`` of
    a long series); None for anything :func:`read` must read whole: a zip, a single file,
    a series with uneven gaps. The same voxels, affine, metadata and patient as ``read``."""
    from miss.io import dicom_stack
    from miss.io.dicom_files import open_source

    if not path.is_dir():
        return None
    with open_source(path) as entries:
        groups, notes = _grouped_headers(path, entries)
    uid = _choose(path, groups, series)
    _refuse_multiframe(groups[uid])
    stack = dicom_stack.stream_stack(path, [(h.entry, h.ds) for h in groups[uid]])
    if stack is None:
        return None
    meta = streamed_meta("dicom", notes + stack.notes, **_series_meta(groups, uid, stack.rescale))
    checked = checked_affine(path, stack.affine, "dicom")
    patient = _patient(groups, uid)
    return Streamed(
        stack.dims, stack.dtype, checked, stack.planes, lambda lo, hi: meta, "dicom", patient
    )


def _patient(groups: dict[str, list[Header]], uid: str) -> dict[str, str]:
    """The identifying attributes of series ``uid``'s first slice (``Volume.patient``),
    each followed by every other value any file of any series found holds for it
    (backslash-joined, as DICOM joins values): a zip may mix patients, and the other
    series' descriptions are listed too, so all their identity is cut out of them."""
    first = groups[uid][0].ds
    found = {tag: dict.fromkeys(_values(first, tag)) for tag in PATIENT_TAGS}
    for headers in groups.values():
        for header in headers:
            for tag in PATIENT_TAGS:
                found[tag].update(dict.fromkeys(_values(header.ds, tag)))
    return {tag: "\\".join(values) for tag, values in found.items()}


def _values(ds: Dataset, tag: str) -> list[str]:
    """The non-empty values of ``tag`` in ``ds`` (a multi-valued one split)."""
    text = _text(ds.get(tag, "") or "")
    return [v for v in text.split("\\") if v.strip()]


def _series_meta(
    groups: dict[str, list[Header]], uid: str, rescale: tuple[float, float]
) -> dict[str, Any]:
    """The ``meta`` of series ``uid`` beyond the defaults (read whole or streamed alike)."""
    first = groups[uid][0].ds
    return {
        "modality": str(first.get("Modality", "")),
        "units": "HU" if first.get("Modality") == "CT" else "",
        "rescale": rescale,
        "series_description": str(first.get("SeriesDescription", "")),
        "body_part": str(first.get("BodyPartExamined", "") or ""),
        "series_uid": uid,
        "study_uid": str(first.get("StudyInstanceUID", "")),
        "frame_of_reference": str(first.get("FrameOfReferenceUID", "")),
        "series": [_describe(u, h) for u, h in groups.items()],
        "burned_in_annotation": any(_burned_in(h.ds) for h in groups[uid]),
        "private_tags": sum(1 for element in first if element.tag.is_private),
    }


def _text(value: Any) -> str:
    """A header value as text; multi-valued ones joined by backslash, as DICOM stores them."""
    from pydicom.multival import MultiValue

    if isinstance(value, MultiValue | list | tuple):
        return "\\".join(str(v) for v in value)
    return str(value)


def _burned_in(ds: Dataset) -> bool:
    """The slice says its pixels show text (patient name, dates) burned into the image."""
    return str(ds.get("BurnedInAnnotation", "") or "").strip().upper() == "YES"


def _grouped_headers(path: Path, entries: list[Entry]) -> tuple[dict[str, list[Header]], list[str]]:
    """Headers of every image file, grouped by series UID (largest series first)."""
    headers: list[Header] = []
    rejected = 0
    with recorded_warnings("pydicom") as notes:
        for entry in entries:
            ds = _read_header(entry)
            if ds is None:
                rejected += 1
            else:
                headers.append(Header(entry, ds))
    if not headers:
        raise _no_images(path, len(entries))
    if rejected:
        notes.append(f"skipped {rejected} file(s) that are not DICOM images")
    groups: dict[str, list[Header]] = {}
    for header in headers:
        groups.setdefault(str(header.ds.get("SeriesInstanceUID", "")), []).append(header)
    ranked = sorted(groups.items(), key=lambda item: -len(item[1]))
    return dict(ranked), notes


def _read_header(entry: Entry) -> Dataset | None:
    """The header of an image file, or None for non-DICOM files and non-image objects."""
    from miss.io.dicom_files import read_dataset

    try:
        ds = read_dataset(entry, header_only=True)
        for _ in ds:  # convert every value now: a damaged one skips the file here, not later
            pass
    except MissError:  # an archive member that cannot even be opened: final
        raise
    except Exception:  # not DICOM, or a damaged header: skip the file, the caller counts it
        return None
    if "Rows" not in ds or "Columns" not in ds:
        return None
    return ds


def _refuse_multiframe(headers: list[Header]) -> None:
    """Enhanced (multi-frame) objects keep geometry per frame; SimpleITK may still read them."""
    from miss.io.dicom_files import number

    for header in headers:
        if number(header.ds, "NumberOfFrames", 1) > 1:
            raise UnsupportedFormat(
                f"{header.entry.label} is a multi-frame (enhanced) DICOM object, which this "
                "reader does not stack; export the series as one file per slice."
            )


def _choose(path: Path, groups: dict[str, list[Header]], series: str | None) -> str:
    if series is None:
        return next(iter(groups))
    if series in groups:
        return series
    available = "; ".join(
        f"{uid} ({len(h)} slices, {h[0].ds.get('SeriesDescription', '')!s})"
        for uid, h in groups.items()
    )
    raise BadParameter(
        f"{path.name}: no series with UID {series!r}; available: {available}. "
        "Pass one of these as series= (or none for the largest)."
    )


def _describe(uid: str, headers: list[Header]) -> dict[str, Any]:
    from miss.io.dicom_files import number

    ds = headers[0].ds
    return {
        "uid": uid,
        "description": str(ds.get("SeriesDescription", "")),
        "modality": str(ds.get("Modality", "")),
        "slices": len(headers),
        "dims": (int(number(ds, "Columns")), int(number(ds, "Rows")), len(headers)),
    }


def _no_images(path: Path, scanned: int) -> MissError:
    import zipfile

    if not path.is_dir() and not zipfile.is_zipfile(path):
        # A weak sniff (extension or two magic bytes): let the other readers try.
        return UnsupportedFormat(f"{path.name} is not a DICOM image")
    where = f"folder {path.name}" if path.is_dir() else path.name
    hint = "Pass the folder (or a .zip of it) that holds the series' .dcm files."
    if path.is_dir():
        others = sorted({p.name for pattern in OTHER_VOLUMES for p in path.glob(pattern)})
        if others:
            hint = f"It holds {', '.join(others[:3])}: pass that file instead of the folder."
    return UnreadableVolume(f"{where}: no DICOM images found among {scanned} file(s). {hint}")
