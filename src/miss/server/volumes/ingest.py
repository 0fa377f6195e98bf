"""Turning an upload (or the demo phantom) into a stored volume, read exactly once.

The scan is parsed here and never again: the voxels go to ``data.zarr`` (real units,
(X, Y, Z), chunked and compressed: :mod:`miss.server.storage.chunked`) that jobs and
slice images read, plane by plane, and everything the pages need (affine, spacing,
range, histogram, presets, thumbnail) is gathered from the planes on their way
(:mod:`miss.server.volumes.summary`), so a volume streamed from its file (``miss ingest``) is
never whole in memory. Patient identity is taken off here, at the door (``miss.deid``):
what is stored for sharing carries none, and the original identity goes to the owner's
record in its own table.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
from collections.abc import Iterable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from miss.deid import REMOVED, deidentify, identity_values, remap_uid, scrub, scrub_patterns
from miss.errors import BadParameter, EmptySurface, MissError, UnreadableVolume
from miss.io.common import Streamed
from miss.io.confined import Confinement, Limits, parse_upload
from miss.server.core.errors import ChooseSeries, UploadTooLarge
from miss.server.storage import chunked
from miss.server.storage.db import VolumeRow
from miss.server.storage.store import DATA, Store, write_atomic
from miss.server.volumes import imaging
from miss.server.volumes.summary import Summary
from miss.server.volumes.uploads import Upload
from miss.types import Volume

#: How uploads are read here: the confinement found at start and the child's limits.
Reading = tuple[Confinement, Limits]

DEMO_NAME = "Demo head phantom (synthetic CT)"
DEMO_SLUG = "demo-head"
#: Name of the server key under which DICOM UIDs are remapped (``Store.secret``).
UID_KEY = "uid-remap"
_META_KEYS = (
    "modality",
    "units",
    "series_description",
    "body_part",
    "series_uid",
    "study_uid",  # remapped, as the series UID: a model sent back finds its study by them
    "frame_of_reference",
    "series",
    "source_format",
    "notes",
)


def source_hash(data: np.ndarray, affine: np.ndarray) -> str:
    """SHA-256 of the voxels (Fortran order, as stored) and the affine: the provenance
    "hash of the source series", which names the data without naming the patient."""
    digest = hashlib.sha256(np.ascontiguousarray(np.asfortranarray(data).T).data)
    digest.update(np.ascontiguousarray(affine, dtype="<f8").data)
    return digest.hexdigest()


def describe(volume: Volume, hist: dict[str, Any], summary: Summary) -> dict[str, Any]:
    """What the API and the workers need to know about a volume, without patient fields;
    ``summary`` holds the figures of its voxels (gathered as they were stored)."""
    units, modality = str(volume.meta.get("units", "")), str(volume.meta.get("modality", ""))
    info: dict[str, Any] = {
        "dims": list(volume.dims),
        "spacing": list(volume.spacing),
        "affine": volume.affine.tolist(),
        "range": [summary.lo, summary.hi],
        "dtype": str(summary.dtype),
        "nbytes": int(np.prod(summary.dims)) * summary.dtype.itemsize,
        **{key: volume.meta.get(key, "") for key in _META_KEYS},
        "window": imaging.default_window(hist),
        "presets": imaging.presets(hist, units, modality),
        "scale": imaging.scale(hist, modality, units),
        "views": imaging.views(volume.affine, volume.dims),
        "burned_in_annotation": bool(volume.meta.get("burned_in_annotation", False)),
        "source_sha256": summary.source_sha256,
    }
    info["series"] = [_jsonable(s) for s in info["series"] or []]
    return _jsonable(info)


def _jsonable(value: Any) -> Any:
    """Tuples and numpy scalars, as DICOM metadata tends to hold, to plain JSON values."""
    return json.loads(
        json.dumps(value, default=lambda o: o.item() if hasattr(o, "item") else str(o))
    )


def stage(
    store: Store, volume: Volume, deid: dict[str, Any] | None = None
) -> tuple[Path, dict[str, Any]]:
    """Write a volume's files into a fresh folder under ``tmp/``; returns (folder, info)."""
    folder = store.tmp_dir()
    try:
        planes = (volume.data[:, :, k] for k in range(volume.dims[2]))
        layout = (volume.dims, volume.data.dtype, volume.affine)
        summary = store_voxels(folder, layout, volume.meta.get("source_format", ""), planes)
        info = finish(folder, volume, summary, deid)
    except BaseException:  # a full disk, a bad volume: no half-written folder stays behind
        shutil.rmtree(folder, ignore_errors=True)
        raise
    return folder, info


def store_voxels(
    folder: Path,
    layout: tuple[tuple[int, int, int], np.dtype, np.ndarray],
    source_format: str,
    planes: Iterable[np.ndarray],
) -> Summary:
    """Write the (X, Y) planes, z in order, of a volume of ``layout`` (dims, dtype,
    affine) as ``folder/data.zarr``; returns their :class:`Summary`."""
    dims, dtype, affine = layout
    summary = Summary(dims, np.dtype(dtype), np.asarray(affine, dtype=float))

    def attributes() -> dict[str, Any]:  # once every plane has passed: the hash is whole
        provenance = {"source_sha256": summary.source_sha256, "source_format": source_format}
        return {"affine": summary.affine, "provenance": provenance}

    chunked.write_planes(folder / DATA, dims, summary.dtype, summary.watch(planes), attributes)
    return summary


def finish(
    folder: Path, volume: Volume, summary: Summary, deid: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Write meta.json, histogram.json and thumbnail.png of the voxels ``summary``
    describes beside them; returns the volume's info (meta.json)."""
    hist = summary.histogram()
    info = describe(volume, hist, summary) | {"deidentification": deid or {}}
    write_atomic(folder / "meta.json", json.dumps(info).encode())
    write_atomic(folder / "histogram.json", json.dumps(hist).encode())
    write_atomic(folder / "thumbnail.png", summary.thumbnail(info["window"]))
    return info


def ingest(
    store: Store,
    upload: Upload,
    work: Path,
    reading: Reading,
    owner_id: str | None = None,
    origin: dict[str, Any] | None = None,
    ask_series: bool = False,
) -> VolumeRow:
    """Read an uploaded file once (confined: :mod:`miss.io.confined`), de-identify it and
    store it for ``owner_id``. ``origin`` (where a PACS series came from: the PACS, the
    original UIDs of its study, series and images) joins the owner-only identity record.

    The child writes the voxels plane by plane where the format allows (a plain NIfTI-1,
    a folder of DICOM slices) and this process stores them plane by plane from its file
    (:func:`store_streamed`, as ``miss ingest`` does): neither holds the whole volume.
    ``ask_series``: files with several DICOM series and no ``series`` field raise
    :class:`ChooseSeries` (409) listing them, instead of reading the largest."""
    assert upload.path is not None
    key = store.secret(UID_KEY)
    try:
        series = original_series(store, work, upload, reading)
        parsed = parse_upload(
            work, upload.path.name, *reading, series=series, whole=False, ask_series=ask_series
        )
        try:
            if parsed.choices:
                raise choose_series(parsed.choices, key)
            shutil.rmtree(work / "unzipped", ignore_errors=True)  # room for the stored copy
            if parsed.streamed is None:  # only a reader that lies answers so
                raise UnreadableVolume("the file reader gave no volume; the file is damaged.")
            check_storable_geometry(parsed.streamed.affine, upload.filename)
            staged, volume, identity, info = store_streamed(
                store, parsed.streamed, key, upload.filename
            )
        finally:
            parsed.close()
    except ChooseSeries:
        raise
    except MissError as exc:  # the server's folders are none of the client's business
        raise type(exc)(public_message(str(exc), work)) from None
    except MemoryError:
        raise UploadTooLarge(
            "the volume does not fit in the server's memory; upload fewer slices."
        ) from None
    patient = identity_values(identity.get("patient", {}))
    # The file name people give a series often is the patient's name: the owner's alone.
    identity = {**identity, "upload_filename": upload.filename}
    if origin:
        identity = {**identity, "origin": origin}
    name = display_name(upload.fields.get("name", ""), volume, patient)
    return store.add_volume(
        staged, name=name, slug=slugify(name), info=info, owner_id=owner_id, identity=identity
    )


def choose_series(found: list[dict[str, Any]], key: bytes) -> ChooseSeries:
    """The question to ask of an upload with several series: each by its remapped UID
    (the one the API shows everywhere; :func:`original_series` maps it back), its
    description with anything like a name or a date taken out, modality and size."""
    listed: list[dict[str, Any]] = [
        {
            "uid": remap_uid(str(s.get("uid", "")), key),
            "description": scrub_patterns(str(s.get("description") or ""))[:200],
            "modality": str(s.get("modality") or "")[:16],
            "slices": int(s.get("slices") or 0),
            "dims": [int(d) for d in s.get("dims") or []][:3],
        }
        for s in found
    ]
    listed.sort(key=lambda s: -int(s["slices"]))  # the largest first, as read by default
    return ChooseSeries(
        f"these files hold {len(listed)} series; choose the one to read and send the "
        "files again with its uid in the form field 'series'.",
        listed,
    )


#: What storing a volume gives: (staged folder, de-identified volume, identity, info).
Stored = tuple[Path, Volume, dict[str, Any], dict[str, Any]]


def ingest_path(store: Store, path: Path, name: str = "") -> VolumeRow:
    """Store the volume at ``path`` (``miss ingest``) as an upload is stored: the same
    de-identification, files and row, no owner (the first administrator's at the next
    start). A plain NIfTI file and a folder of DICOM slices are read plane by plane
    (:func:`miss.io.nifti.stream`, :func:`miss.io.dicom.stream`), so they are never whole
    in memory; other formats are read whole. Read in this process, unconfined: what it
    reads is first checked to lie in the ingested folder (:func:`refuse_links_out`)."""
    refuse_links_out(path)
    key = store.secret(UID_KEY)
    with store.disk_full_as_507():
        staged, volume, identity, info = _stream_in(store, path, key) or _read_in(store, path, key)
    name = display_name(name, volume, identity_values(identity.get("patient", {})))
    identity = {**identity, "upload_filename": path.name}
    return store.add_volume(staged, name=name, slug=slugify(name), info=info, identity=identity)


def refuse_links_out(path: Path) -> None:
    """Refuse to ingest ``path`` when a file its readers may open is a symbolic link (or
    lies below one) that leads out of the ingested folder: every entry of ``path`` if a
    folder (a DICOM series: every file in it is read); for a file, every entry of its
    folder when the file can name others (a detached NRRD or MetaImage header, SimpleITK's
    formats: their header checks allow any name inside the folder), else its namesakes (a
    NIfTI pair's ``.img``). The file named on the command line is taken as given; a zip's
    links are refused as it is unpacked. Raises ``BadParameter`` naming the link."""
    from miss.io import self_contained
    from miss.io.archive import is_zip

    if path.is_dir():
        _refuse_links_in(path, _entries(path))
    elif not is_zip(path):
        if self_contained(path):
            _refuse_links_in(path.parent, _entries(path.parent))
        else:
            stem = path.name.split(".")[0]
            namesakes = (p for p in path.parent.iterdir() if p.name.split(".")[0] == stem)
            _refuse_links_in(path.parent, (str(p) for p in namesakes if p.name != path.name))


def _entries(folder: Path) -> Iterable[str]:
    """Every file and folder under ``folder``, links not followed (each is checked)."""
    for top, dirs, files in os.walk(folder):
        yield from (os.path.join(top, name) for name in (*dirs, *files))


def _refuse_links_in(folder: Path, paths: Iterable[str]) -> None:
    inside = os.path.realpath(folder)
    for link in paths:
        target = os.path.realpath(link)
        if os.path.islink(link) and os.path.commonpath([inside, target]) != inside:
            raise BadParameter(
                f"{link} is a symbolic link to {target}, outside the ingested folder "
                f"{folder}; copy that file into the folder (MISS reads no file out of it)."
            )


def _stream_in(store: Store, path: Path, key: bytes) -> Stored | None:
    """Store a file that can be read plane by plane into a folder under ``tmp/``; None
    for one that cannot (``_read_in`` reads it whole)."""
    from miss.io import dicom, nifti
    from miss.io.common import NotStreamable

    streamed = nifti.stream(path) or (dicom.stream(path) if path.is_dir() else None)
    if streamed is None:
        return None
    try:
        return store_streamed(store, streamed, key, path.name)
    except NotStreamable:  # NaN voxels become the minimum, which only a whole read knows
        return None


def store_streamed(store: Store, streamed: Streamed, key: bytes, name: str) -> Stored:
    """Store a volume that comes plane by plane into a folder under ``tmp/`` (de-identified
    as it is stored: the same files as :func:`stage` of it read whole); ``name`` is the
    file's name, for messages. Raises what the planes raise, leaving no folder behind."""
    folder = store.tmp_dir()
    try:
        layout = (streamed.dims, streamed.dtype, streamed.affine)
        summary = store_voxels(folder, layout, streamed.source_format, streamed.planes)
        check_storable_range(summary.lo, summary.hi, name)
        lazy, _, _ = chunked.open_array(folder / DATA)
        meta = streamed.meta(summary.lo, summary.hi)
        # a lazy (X, Y, Z) array: Volume's data is typed as the numpy array it mostly is
        volume = Volume(lazy, streamed.affine, meta=meta, patient=streamed.patient)  # type: ignore[arg-type]
        clean = deidentify(volume, key)
        info = finish(folder, clean.volume, summary, clean.report)
    except BaseException:  # a full disk, a bad slice: no half-written folder stays behind
        shutil.rmtree(folder, ignore_errors=True)
        raise
    return folder, clean.volume, clean.identity, info


def _read_in(store: Store, path: Path, key: bytes) -> Stored:
    """Store a file read whole (any format ``miss.io`` reads) into a folder under ``tmp/``."""
    from miss.io import load_volume

    volume = load_volume(path)
    check_storable(volume, path.name)
    clean = deidentify(volume, key)
    staged, info = stage(store, clean.volume, clean.report)
    return staged, clean.volume, clean.identity, info


def public_message(message: str, work: Path) -> str:
    """A reader's message without the server's folders: paths inside the upload are
    shown relative to it, the folder a zip was unpacked into is called "the zip"."""
    said = message.replace(f"{work}/unzipped/", "").replace(f"{work}/", "")
    return said.replace("folder unzipped:", "the zip:").replace("unzipped: ", "")


def check_storable(volume: Volume, name: str) -> None:
    """Refuse what no reader should hand on but the pages could not show: a geometry
    that is not finite or has no extent, values that are not finite or all the same."""
    check_storable_geometry(volume.affine, name)
    check_storable_range(*volume.value_range(), name)


def check_storable_geometry(affine: np.ndarray, name: str) -> None:
    """:func:`check_storable`'s refusal of a geometry that is not finite or has no extent."""
    affine = np.asarray(affine, dtype=float)
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    if not np.isfinite(affine).all() or not (spacing > 0).all():
        steps = ", ".join(f"{s:g}" for s in spacing)
        raise UnreadableVolume(
            f"{name}: the voxel geometry is unusable (voxel steps {steps} mm); fix the "
            "voxel spacing and orientation in its header."
        )


def check_storable_range(lo: float, hi: float, name: str) -> None:
    """:func:`check_storable`'s refusal of values that are not finite or all the same."""
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise UnreadableVolume(
            f"{name}: the voxel values are not finite ({lo:g}..{hi:g}); re-export the volume."
        )
    if lo == hi:
        raise EmptySurface(
            f"{name}: every voxel has the value {lo:g}; there is no surface to draw in it. "
            "Check that the file holds the image, not an empty mask."
        )


def original_series(store: Store, work: Path, upload: Upload, reading: Reading) -> str | None:
    """The original UID of the series asked for. The API lists series by their remapped
    UIDs (``2.25.``...), so a client that picks one from a listing sends that; the reader
    needs the UID in the files (listed by a confined child: the key stays here)."""
    wanted = upload.fields.get("series") or None
    if not wanted or not wanted.startswith("2.25."):
        return wanted
    assert upload.path is not None
    key = store.secret(UID_KEY)
    listed = parse_upload(work, upload.path.name, *reading, mode="series").series
    for entry in listed:
        if remap_uid(str(entry.get("uid", "")), key) == wanted:
            return str(entry["uid"])
    return wanted


def register_demo(store: Store, owner_id: str | None = None) -> None:
    """Register the synthetic phantom, so a fresh install has something to show."""
    from miss.demo import phantom

    staged, info = stage(store, phantom())
    store.add_volume(staged, name=DEMO_NAME, slug=DEMO_SLUG, info=info, owner_id=owner_id)


def display_name(name: str, volume: Volume, identity: list[str]) -> str:
    """The name to list: the ``name`` the uploader typed, else :func:`volume_name`.

    Never the file's or a folder's name: people name those after the patient, in
    spellings no header gives ("Smith_John_1970.zip", "Jörg Müller.nii"); the file name
    goes to the owner-only identity record. A typed name that contains any identity
    value, or looks like a person name or a date, is replaced too: shared models must
    not carry identity. ``identity`` is ``miss.deid.identity_values`` of the header.
    """
    name = name.strip()
    spaced = re.sub(r"[_\-.]+", " ", name)  # "_" and "-" where a header has "^" and spaces
    if name and all(scrub_patterns(scrub(text, identity)) == text for text in (name, spaced)):
        return name[:200]
    return volume_name(volume)


#: How a person names a file format, for a scan whose header gives no modality (the
#: library shows the same words: js/format.js ``kindOf``).
FORMAT_NAMES = {"dicom": "DICOM", "nifti": "NIfTI", "nrrd": "NRRD", "metaimage": "MetaImage"}


def volume_name(volume: Volume) -> str:
    """A name from what the de-identified volume says of itself: modality, body part and
    series description ("CT HEAD Axial 5 mm"). A description that had anything cut out
    is left out (what is left reads as a riddle about what was cut); without one, the
    modality (else the file's format: "NIfTI"), body part and the upload's time ("CT HEAD
    volume, uploaded 2026-11-24 14:05"), which says when it came, never when the patient
    was scanned."""
    meta = volume.meta
    modality = str(meta.get("modality") or "").strip()
    kind = modality or FORMAT_NAMES.get(str(meta.get("source_format", "")), "Scan")
    body = str(meta.get("body_part") or "").strip()
    description = str(meta.get("series_description") or "").strip()
    body = "" if REMOVED in body else body
    description = "" if REMOVED in description else description
    if body and body.lower() in description.lower():
        body = ""
    if description:
        said = " ".join(p for p in (modality, body, description) if p)
        return " ".join("".join(c for c in said if c.isprintable()).split())[:200] or "Scan"
    when = datetime.now(UTC).strftime("%Y-%m-%d %H:%M")
    return f"{' '.join(p for p in (kind, body) if p)} volume, uploaded {when}"


def slugify(name: str) -> str:
    """A file-name-safe short form of a name: ``CT_pitch`` -> ``ct-pitch``."""
    slug = re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")
    return slug[:40].rstrip("-") or "volume"
