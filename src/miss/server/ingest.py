"""Turning an upload (or the demo phantom) into a stored volume, read exactly once.

The scan is parsed here and never again: the voxels go to ``data.npy`` (real units,
(X, Y, Z), Fortran order) that jobs and slice images memory-map, and everything the
pages need (affine, spacing, range, histogram, presets, thumbnail) is computed while
the array is in memory. Patient-identifying fields are dropped here, at the door.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from miss.errors import MissError
from miss.io import load_volume
from miss.server import imaging
from miss.server.db import VolumeRow
from miss.server.errors import UploadTooLarge
from miss.server.store import Store, write_atomic
from miss.server.uploads import Upload, extract_zip, is_zip, pick_source, volume_suffix
from miss.types import Volume

DEMO_NAME = "Demo head phantom (synthetic CT)"
DEMO_SLUG = "demo-head"
_META_KEYS = (
    "modality",
    "units",
    "series_description",
    "series_uid",
    "series",
    "source_format",
    "notes",
)


def describe(volume: Volume, hist: dict[str, Any]) -> dict[str, Any]:
    """What the API and the workers need to know about a volume, without patient fields."""
    lo, hi = volume.value_range()
    info: dict[str, Any] = {
        "dims": list(volume.dims),
        "spacing": list(volume.spacing),
        "affine": volume.affine.tolist(),
        "range": [lo, hi],
        "dtype": str(volume.data.dtype),
        "nbytes": int(volume.data.nbytes),
        **{key: volume.meta.get(key, "") for key in _META_KEYS},
        "window": imaging.default_window(hist),
        "presets": imaging.presets(hist, str(volume.meta.get("units", ""))),
        "views": imaging.views(volume.affine, volume.dims),
    }
    info["series"] = [_jsonable(s) for s in info["series"] or []]
    return _jsonable(info)


def _jsonable(value: Any) -> Any:
    """Tuples and numpy scalars, as DICOM metadata tends to hold, to plain JSON values."""
    return json.loads(
        json.dumps(value, default=lambda o: o.item() if hasattr(o, "item") else str(o))
    )


def stage(store: Store, volume: Volume) -> tuple[Path, dict[str, Any]]:
    """Write a volume's files into a fresh folder under ``tmp/``; returns (folder, info)."""
    folder = store.tmp_dir()
    hist = imaging.histogram(volume.data)
    info = describe(volume, hist)
    np.save(folder / "data.npy", np.asfortranarray(volume.data), allow_pickle=False)
    write_atomic(folder / "meta.json", json.dumps(info).encode())
    write_atomic(folder / "histogram.json", json.dumps(hist).encode())
    write_atomic(
        folder / "thumbnail.png", imaging.thumbnail(volume.data, volume.affine, info["window"])
    )
    return folder, info


def ingest(store: Store, upload: Upload, work: Path, max_unzipped: int) -> VolumeRow:
    """Read an uploaded file once and store it; returns the new volume's row."""
    assert upload.path is not None
    source = upload.path
    if is_zip(source):
        unpacked = work / "unzipped"
        unpacked.mkdir()
        extract_zip(source, unpacked, max_unzipped)
        source.unlink()  # the zip is no longer needed: halve the disk used meanwhile
        source = pick_source(unpacked)
    try:
        volume = load_volume(source, series=upload.fields.get("series") or None)
    except MissError as exc:  # the server's folders are none of the client's business
        raise type(exc)(str(exc).replace(f"{work}/", "")) from None
    except MemoryError:
        raise UploadTooLarge(
            "the volume does not fit in the server's memory; upload fewer slices."
        ) from None
    name = display_name(upload, volume)
    staged, info = stage(store, volume)
    return store.add_volume(staged, name=name, slug=slugify(name), info=info)


def register_demo(store: Store) -> None:
    """Register the synthetic phantom, so a fresh install has something to show."""
    from miss.demo import phantom

    staged, info = stage(store, phantom())
    store.add_volume(staged, name=DEMO_NAME, slug=DEMO_SLUG, info=info)


def display_name(upload: Upload, volume: Volume) -> str:
    """The name to list: the ``name`` field, else the file name without its extensions.

    A file name that contains the patient's name (``SMITH_JOHN.zip``) is replaced by the
    modality and series description: shared models must not carry identity.
    """
    name = upload.fields.get("name", "").strip()
    if not name:
        filename = Path(upload.filename.replace("\\", "/")).name
        suffix = volume_suffix(Path(filename)) or (
            ".zip" if filename.lower().endswith(".zip") else ""
        )
        name = filename[: len(filename) - len(suffix)] if suffix else filename
    tokens = re.split(r"[\^\s,]+", str(volume.patient.get("PatientName", "") or ""))
    if any(len(t) >= 3 and t.lower() in name.lower() for t in tokens):
        meta = volume.meta
        name = (
            " ".join(filter(None, [meta.get("modality"), meta.get("series_description")])) or "Scan"
        )
    return name[:200] or "Scan"


def slugify(name: str) -> str:
    """A file-name-safe short form of a name: ``CT_pitch`` -> ``ct-pitch``."""
    slug = re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")
    return slug[:40].rstrip("-") or "volume"
