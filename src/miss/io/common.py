"""What every reader shares: the ``Volume`` it hands back and the shape of its metadata.

Readers decode their format into an (X, Y, Z) array plus an LPS affine and call
:func:`make_volume`, which enforces the things the rest of MISS relies on (3-D, at
least two voxels along every axis, native byte order, Fortran order) and fills every
``meta`` key so that consumers never need ``.get``.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from miss.errors import BadParameter, UnreadableVolume
from miss.types import Volume

#: Flips the first two axes: RAS <-> LPS (its own inverse).
RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])


def make_volume(
    path: Path,
    data: np.ndarray,
    affine: np.ndarray,
    source_format: str,
    notes: Sequence[str] = (),
    patient: dict[str, Any] | None = None,
    **meta: Any,
) -> Volume:
    """Wrap decoded voxels into a ``Volume`` with complete metadata.

    Parameters
    ----------
    path : Path
        The file or folder read; only its name is used, in error messages.
    data : (X, Y, Z) array
        Voxel values in real units. Made native-endian and Fortran-ordered here
        (a no-op for readers that already return an F-contiguous view).
    affine : (4, 4) array
        Voxel index to LPS millimetres.
    source_format : str
        ``"dicom"``, ``"nifti"``, ``"nrrd"``, ``"metaimage"`` or ``"itk"``.
    notes : sequence of str
        What the reader had to assume or change, in plain words.
    patient : dict, optional
        Patient-identifying fields (DICOM only).
    **meta
        Overrides for the keys of :func:`default_meta`; ``series`` defaults to a
        one-entry list describing this volume.
    """
    if data.ndim != 3:
        raise UnreadableVolume(
            f"{path.name}: holds a {data.ndim}-D image of shape {data.shape}; "
            "MISS needs a 3-D volume (a stack of slices)."
        )
    if min(data.shape) < 2:
        raise UnreadableVolume(
            f"{path.name}: the volume is {'x'.join(map(str, data.shape))} voxels; "
            "a surface needs at least 2 voxels along every axis (at least 2 slices)."
        )
    if not data.dtype.isnative:
        data = data.astype(data.dtype.newbyteorder("="))
    data = np.asfortranarray(data)
    full = default_meta(source_format) | meta
    full["notes"] = list(notes)
    if not full["series"]:
        full["series"] = [describe(full, data.shape)]
    return Volume(data=data, affine=np.asarray(affine, float), meta=full, patient=patient or {})


def default_meta(source_format: str) -> dict[str, Any]:
    """Every ``meta`` key a reader may fill, with the value meaning "unknown"."""
    return {
        "modality": "",
        "units": "",
        "rescale": (1.0, 0.0),
        "series_description": "",
        "series_uid": "",
        "study_uid": "",
        "frame_of_reference": "",
        "series": [],
        "source_format": source_format,
        "notes": [],
    }


def describe(meta: dict[str, Any], shape: tuple[int, ...]) -> dict[str, Any]:
    """One ``list_series`` entry: uid, description, modality, slices, dims (x, y, z)."""
    return {
        "uid": meta.get("series_uid", ""),
        "description": meta.get("series_description", ""),
        "modality": meta.get("modality", ""),
        "slices": int(shape[2]),
        "dims": tuple(int(n) for n in shape[:3]),
    }


def no_series(path: Path, series: str | None, fmt: str) -> None:
    """Refuse ``series=`` for formats that hold exactly one volume."""
    if series is not None:
        raise BadParameter(
            f"{path.name}: series={series!r} was given, but a {fmt} file holds a single "
            "volume; leave series unset (it selects among DICOM series only)."
        )


def zyx_to_xyz(stack: np.ndarray) -> np.ndarray:
    """View a C-ordered (Z, Y, X) stack as (X, Y, Z); the view is Fortran-ordered, no copy."""
    return stack.transpose(2, 1, 0)


def affine_from(
    directions: np.ndarray, spacing: Sequence[float], origin: Sequence[float]
) -> np.ndarray:
    """(4, 4) affine from unit axis directions (3x3, one axis per column), mm steps, origin."""
    aff = np.eye(4)
    aff[:3, :3] = np.asarray(directions, float) * np.asarray(spacing, float)[None, :]
    aff[:3, 3] = origin
    return aff


@contextmanager
def recorded_warnings(library: str) -> Iterator[list[str]]:
    """Collect a library's warnings (odd tag values in real scans) as notes, not noise.

    The list yielded is filled when the block ends: at most 5 distinct messages,
    each prefixed with ``library``.
    """
    notes: list[str] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield notes
    distinct = dict.fromkeys(f"{library}: {w.message}" for w in caught)
    notes.extend(list(distinct)[:5])


def integer_dtype(raw_range: tuple[int, int], slope: float, intercept: float) -> np.dtype:
    """The narrower of int16/int32 that holds ``raw * slope + intercept`` over the raw range."""
    lo, hi = sorted((raw_range[0] * slope + intercept, raw_range[1] * slope + intercept))
    for dtype in (np.int16, np.int32):
        info = np.iinfo(dtype)
        if info.min <= lo and hi <= info.max:
            return np.dtype(dtype)
    return np.dtype(np.int64)
