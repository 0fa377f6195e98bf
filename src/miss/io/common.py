"""What every reader shares: the ``Volume`` it hands back and the shape of its metadata.

Readers decode their format into an (X, Y, Z) array plus an LPS affine and call
:func:`make_volume`, which enforces the things the rest of MISS relies on (3-D, at
least two voxels along every axis, native byte order, Fortran order) and fills every
``meta`` key so that consumers never need ``.get``.
"""

from __future__ import annotations

import math
import re
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from miss.errors import BadParameter, UnreadableVolume
from miss.types import Volume

#: Flips the first two axes: RAS <-> LPS (its own inverse).
RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])
#: Most voxels a header may declare (a 1024 x 1024 x 4096 scan, 8 GB as int16): a sanity
#: bound that refuses absurd sizes before anything is allocated.
MAX_VOXELS = 2**32
#: DEFLATE (gzip, zlib) cannot do better than about 1032:1, so n compressed bytes never
#: inflate to more than this many times n; a header declaring more is damaged.
DEFLATE_MAX_RATIO = 1032
#: Largest coordinate or step (mm) an affine may hold: 1000 km, far beyond any scanner.
MAX_MM = 1e9
#: Where each format keeps the geometry a degenerate affine comes from (for messages).
GEOMETRY_FIELDS = {
    "dicom": "PixelSpacing, ImageOrientationPatient and ImagePositionPatient",
    "nifti": "pixdim, qform and sform",
    "nrrd": "space directions, spacings and space origin",
    "metaimage": "ElementSpacing, TransformMatrix and Offset",
}


class NotStreamable(Exception):
    """A file read plane by plane turned out to need the whole volume (NaN voxels are
    replaced by the volume's minimum): read it whole instead."""


@dataclass(frozen=True)
class Streamed:
    """A volume read plane by plane (for files too big to hold whole): its layout and its
    (X, Y) planes, z in order, made as :func:`make_volume` makes a whole one (native byte
    order, finite values). ``meta(lo, hi)`` is its metadata once the planes have passed
    and its value range is known (NIfTI tells CT by it)."""

    dims: tuple[int, int, int]
    dtype: np.dtype
    affine: np.ndarray  # (4, 4), voxel index to LPS mm, checked
    planes: Iterator[np.ndarray]
    meta: Callable[[float, float], dict[str, Any]]
    source_format: str
    patient: dict[str, Any] = field(default_factory=dict)  # identifying fields (DICOM)


def streamed_meta(source_format: str, notes: Sequence[str], **meta: Any) -> dict[str, Any]:
    """The metadata :func:`make_volume` gives (``**meta`` over the defaults)."""
    full = default_meta(source_format) | meta
    full["notes"] = list(notes)
    return full


def checked_affine(path: Path, affine: np.ndarray, source_format: str) -> np.ndarray:
    """``affine`` as float64 (4, 4), refused as :func:`make_volume` refuses it."""
    return _checked_affine(path, affine, source_format)


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
            "MISS needs a 3-D volume (a stack of slices): pass the whole scan instead."
        )
    if min(data.shape) < 2:
        raise UnreadableVolume(
            f"{path.name}: the volume is {'x'.join(map(str, data.shape))} voxels; "
            "a surface needs at least 2 voxels along every axis (at least 2 slices): pass "
            "the whole scan, not a single slice."
        )
    notes = list(notes)
    data = finite_values(path, _real(path, data), notes)
    affine = _checked_affine(path, affine, source_format)
    if not data.dtype.isnative:
        data = data.astype(data.dtype.newbyteorder("="))
    data = np.asfortranarray(data)
    full = default_meta(source_format) | meta
    full["notes"] = notes
    if not full["series"]:
        full["series"] = [describe(full, data.shape)]
    return Volume(data=data, affine=affine, meta=full, patient=patient or {})


def _real(path: Path, data: np.ndarray) -> np.ndarray:
    """Real numbers per voxel: booleans become uint8; complex, colour or records are refused."""
    if data.dtype.kind == "b":
        return data.astype(np.uint8)
    if data.dtype.kind not in "iuf":
        raise UnreadableVolume(
            f"{path.name}: its voxels are {data.dtype} ({_KIND_NAMES.get(data.dtype.kind, 'not numbers')}), "
            "not one real value each; convert it to a greyscale (scalar) volume first."
        )
    return data


_KIND_NAMES = {"c": "complex numbers", "V": "several values, e.g. colour", "O": "objects"}


def _checked_affine(path: Path, affine: np.ndarray, source_format: str) -> np.ndarray:
    """The affine as float64, refused when non-finite or degenerate (a flat or empty grid)."""
    aff = np.asarray(affine, float)
    fields = GEOMETRY_FIELDS.get(source_format, "voxel spacing and orientation")
    if aff.shape != (4, 4) or not np.isfinite(aff).all() or np.abs(aff).max() > MAX_MM:
        raise UnreadableVolume(
            f"{path.name}: the voxel-to-millimetre geometry is not finite or beyond "
            f"{MAX_MM / 1e6:g} km; fix the header's {fields}."
        )
    steps = np.linalg.norm(aff[:3, :3], axis=0)
    # |det| / product of step lengths is 1 for orthogonal axes, ~cos(tilt) under a gantry tilt.
    if steps.min() <= 0 or abs(np.linalg.det(aff[:3, :3])) <= 1e-6 * float(np.prod(steps)):
        raise UnreadableVolume(
            f"{path.name}: the voxel-to-millimetre geometry is degenerate (voxel steps "
            f"{', '.join(f'{s:g}' for s in steps)} mm, or axes parallel); fix the header's {fields}."
        )
    return aff


def finite_values(path: Path, values: np.ndarray, notes: list[str]) -> np.ndarray:
    """Replace NaN by the smallest finite value and +/-Inf by the extreme finite values.

    Checked slice by slice so that a large float volume needs no full-size mask when it is
    all finite (the usual case).
    """
    if values.dtype.kind != "f" or all(
        np.isfinite(values[..., k]).all() for k in range(values.shape[-1])
    ):
        return values
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        raise UnreadableVolume(
            f"{path.name}: every voxel is NaN or infinite; there is nothing to draw. Check "
            "that the file holds the image itself, not an empty result of a failed computation."
        )
    lo, hi = finite.min(), finite.max()
    notes.append(
        f"replaced {int(np.isnan(values).sum())} NaN voxel(s) by the minimum {lo:g} and "
        f"{int(np.isinf(values).sum())} infinite voxel(s) by the finite extremes"
    )
    return np.nan_to_num(values, nan=lo, posinf=hi, neginf=lo)


def check_declared_size(
    path: Path,
    shape: Sequence[float],
    itemsize: int,
    compressed_bytes: int | None = None,
    fix: str = "fix the sizes in its header",
) -> None:
    """Refuse header sizes that are absurd, before anything is allocated or inflated.

    Parameters
    ----------
    shape : the declared voxel counts (any number of axes, components included)
    itemsize : bytes per value
    compressed_bytes : for gzip/zlib data, the compressed bytes on disk; the declared
        size must fit in ``DEFLATE_MAX_RATIO`` times that.
    """
    count = math.prod(int(n) for n in shape)  # Python ints: no int64 overflow
    size = "x".join(str(int(n)) for n in shape)
    if count > MAX_VOXELS:
        raise UnreadableVolume(
            f"{path.name}: the header declares {size} = {count:.3g} voxels, more than the "
            f"{MAX_VOXELS:.3g} MISS reads; the header is damaged or this is not a scan: {fix}."
        )
    if compressed_bytes is not None and count * itemsize > DEFLATE_MAX_RATIO * compressed_bytes:
        raise UnreadableVolume(
            f"{path.name}: the header declares {size} voxels ({_bytes(count * itemsize)}), "
            f"which {_bytes(compressed_bytes)} of compressed data cannot hold; the header is "
            f"damaged or the data incomplete: copy the file again or {fix}."
        )


def _bytes(n: int) -> str:
    for unit, scale in (("GB", 1024**3), ("MB", 1024**2), ("KB", 1024)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n} bytes"


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
    directions: np.ndarray,
    spacing: Sequence[float] | np.ndarray,
    origin: Sequence[float] | np.ndarray,
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
    # A ResourceWarning is the garbage collector's about any object that happened to go
    # then (a socket of the server's, say), never the scan's: passed on, not a note.
    for w in caught:
        if issubclass(w.category, ResourceWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)
    said = (w for w in caught if not issubclass(w.category, ResourceWarning))
    distinct = dict.fromkeys(f"{library}: {_unquoted(str(w.message))}" for w in said)
    notes.extend(list(distinct)[:5])


#: A quoted value in a library's warning ("Invalid value for VR UI: 'Roe^Jane'").
_QUOTED = re.compile(r"(?<![A-Za-z])(?:'[^']*'|\"[^\"]*\")")


def _unquoted(message: str) -> str:
    """A warning without the header values it quotes: notes are shown to whoever sees
    the volume, and the value may be a patient's name in the wrong field."""
    return _QUOTED.sub("[value]", message)


def integer_dtype(raw_range: tuple[int, int], slope: float, intercept: float) -> np.dtype:
    """The narrower of int16/int32 that holds ``raw * slope + intercept`` over the raw range."""
    lo, hi = sorted((raw_range[0] * slope + intercept, raw_range[1] * slope + intercept))
    for dtype in (np.int16, np.int32):
        info = np.iinfo(dtype)
        if info.min <= lo and hi <= info.max:
            return np.dtype(dtype)
    return np.dtype(np.int64)
