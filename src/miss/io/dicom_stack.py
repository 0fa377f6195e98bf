"""Stack the slices of one DICOM series into an (X, Y, Z) array and its LPS affine.

Slices are ordered by their position along the slice normal (never by file name or
InstanceNumber), duplicates are dropped, pixel values are rescaled to real units, and
uneven gaps are resampled onto a regular grid (see :mod:`miss.io.slices`).
"""

from __future__ import annotations

import math
import re
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydicom.dataset import Dataset

from miss.errors import MissError, UnreadableVolume
from miss.io import codecs, slices
from miss.io.common import MAX_MM, check_declared_size, integer_dtype, recorded_warnings, zyx_to_xyz
from miss.io.dicom_files import Entry, number, read_dataset


@dataclass(frozen=True)
class Stack:
    """A stacked series.

    Attributes
    ----------
    data : (X, Y, Z) array, Fortran-ordered view of a (Z, Y, X) stack, real units
    affine : (4, 4) float array, voxel index to LPS mm (sheared under gantry tilt)
    rescale : (slope, intercept) of the first slice
    notes : list of str
    """

    data: np.ndarray
    affine: np.ndarray
    rescale: tuple[float, float]
    notes: list[str]


@dataclass(frozen=True)
class _Plan:
    """What stacking a series needs before any pixel is decoded."""

    entries: list[Entry]  # the kept slices, ordered along the normal
    positions: np.ndarray  # their positions along it, mm
    grid: slices.Grid
    affine: np.ndarray
    notes: list[str]


def _plan(path: Path, files: list[tuple[Entry, Dataset]]) -> _Plan:
    """Order and de-duplicate the slices, check the size, plan the grid and the affine."""
    notes: list[str] = []
    files = _placed(path, _consistent(files, notes), notes)
    normal = slices.slice_normal(_orientation(files[0][1]))
    origins = np.array([_position(ds) for _, ds in files])
    order, positions = slices.order_along(origins, normal)
    duplicate = slices.duplicate_mask(positions)
    if duplicate.any():
        notes.append(f"dropped {int(duplicate.sum())} slice(s) at the same position as another")
    keep, positions = order[~duplicate], positions[~duplicate]
    _need_two(path, len(keep), " at distinct positions")
    first = files[keep[0]][1]
    check_declared_size(
        path,
        (number(first, "Columns"), number(first, "Rows"), len(keep)),
        2,
        fix="check the series' Rows and Columns",
    )
    _check_compressed(path, first, len(keep))
    try:
        grid = slices.plan_grid(positions, origins[keep])
    except ValueError as exc:
        raise UnreadableVolume(
            f"{path.name}: {exc}; export the series again, or pass only the slices of one stack."
        ) from exc
    affine = _affine(first, origins[keep[0]], grid.step, normal, notes)
    return _Plan([files[i][0] for i in keep], positions, grid, affine, notes)


def assemble(path: Path, files: list[tuple[Entry, Dataset]]) -> Stack:
    """Order, de-duplicate, decode, rescale and (if gaps are uneven) resample a series.

    Parameters
    ----------
    path : Path
        What the user passed (for messages).
    files : list of (Entry, header Dataset)
        The series' files, headers read without pixels, in any order.
    """
    plan = _plan(path, files)
    notes = list(plan.notes)
    pixels, scales = _decode(path, plan.entries, notes)
    zyx, rescale = rescaled_stack(pixels, scales, notes)
    if plan.grid.resampled:
        zyx = slices.resample(zyx, plan.positions, plan.grid.positions)
    return Stack(zyx_to_xyz(zyx), plan.affine, rescale, notes + plan.grid.notes)


@dataclass(frozen=True)
class StreamedStack:
    """A series read slice by slice: its layout and its (X, Y) planes, z in order, each
    rescaled as :func:`assemble` rescales it (the same dtype and values)."""

    dims: tuple[int, int, int]
    dtype: np.dtype
    affine: np.ndarray
    rescale: tuple[float, float]
    notes: list[str]
    planes: Iterator[np.ndarray]


def stream_stack(path: Path, files: list[tuple[Entry, Dataset]]) -> StreamedStack | None:
    """The series as planes decoded one at a time (twice: once for the value range that
    picks the dtype, once to hand on), never the whole stack in memory; None for a series
    with uneven gaps (resampling needs its neighbours: :func:`assemble` reads it whole)."""
    plan = _plan(path, files)
    if plan.grid.resampled:
        return None
    notes = list(plan.notes)
    raw, scales, integer = None, [], True
    for array, scale in _decoded(path, plan.entries, notes):
        scales.append(scale)
        integer = integer and array.dtype.kind in "iub"
        if integer:
            lo, hi = int(array.min()), int(array.max())
            raw = (lo, hi) if raw is None else (min(raw[0], lo), max(raw[1], hi))
        rows, columns = array.shape
    dtype, uniform = _stack_dtype(scales, raw or (0, 0), integer)
    if not uniform:
        notes.append(RESCALED_APART)
    planes = (_rescaled(array, scale, dtype).T for array, scale in _decoded(path, plan.entries, []))
    dims = (columns, rows, len(plan.entries))
    return StreamedStack(dims, dtype, plan.affine, scales[0], notes + plan.grid.notes, planes)


def _check_compressed(path: Path, first: Dataset, count: int) -> None:
    """Compressed pixels (JPEG, JPEG 2000, RLE) decode to the size the headers declare
    whatever the files hold: the declared stack against the bytes on disk, before any
    slice is decoded (:mod:`miss.io.codecs`)."""
    shape = (int(number(first, "Columns")), int(number(first, "Rows")), count)
    itemsize = max(int(number(first, "BitsAllocated", 16)) // 8, 1)
    what = f"{'x'.join(map(str, shape))} pixels of {itemsize} byte(s)"
    decoded = math.prod(shape) * itemsize
    codecs.check_decoded(path, decoded, codecs.bytes_on_disk(path), "DICOM files", what)


def _position(ds: Dataset) -> np.ndarray:
    return np.asarray(ds.ImagePositionPatient, float).ravel()


def _orientation(ds: Dataset) -> np.ndarray:
    return np.asarray(ds.ImageOrientationPatient, float).ravel()


def _consistent(
    files: list[tuple[Entry, Dataset]], notes: list[str]
) -> list[tuple[Entry, Dataset]]:
    """Keep the slices sharing the commonest size and orientation (drops scouts mixed in)."""

    def key(ds: Dataset) -> tuple:
        try:
            iop = tuple(np.round(_orientation(ds), 3)) if "ImageOrientationPatient" in ds else None
        except (TypeError, ValueError):
            iop = None
        if iop is not None and not np.isfinite(iop).all():
            iop = None  # NaN never equals itself: it would split every slice into its own group
        return (int(number(ds, "Rows")), int(number(ds, "Columns")), iop)

    counts = Counter(key(ds) for _, ds in files)
    best, _ = counts.most_common(1)[0]
    if len(counts) > 1:
        notes.append(
            f"kept {counts[best]} of {len(files)} slices sharing the commonest size and "
            "orientation; the others differ (scout or reformat images in the same series)"
        )
    return [(e, ds) for e, ds in files if key(ds) == best]


def _placed(
    path: Path, files: list[tuple[Entry, Dataset]], notes: list[str]
) -> list[tuple[Entry, Dataset]]:
    """Keep slices that say where they are (ImagePositionPatient + ImageOrientationPatient)."""
    placed, problems = [], []
    for entry, ds in files:
        problem = _geometry_problem(ds)
        if problem:
            problems.append(f"{entry.label}: {problem}")
        else:
            placed.append((entry, ds))
    if not placed:
        if all("no ImagePositionPatient" in p for p in problems):
            raise UnreadableVolume(
                f"{path.name}: the slices carry no ImagePositionPatient/ImageOrientationPatient, "
                "so they cannot be stacked in space; export the series with geometry tags."
            )
        raise UnreadableVolume(
            f"{path.name}: no slice has a usable position and orientation ({problems[0]}), so "
            "they cannot be stacked in space; export the series again with valid "
            "ImagePositionPatient/ImageOrientationPatient."
        )
    if len(placed) < len(files):
        notes.append(f"skipped {len(files) - len(placed)} slice(s) without position or orientation")
    _need_two(path, len(placed), "")
    return placed


def _geometry_problem(ds: Dataset) -> str:
    """Why a slice's position/orientation cannot place it ("" when they can)."""
    if "ImagePositionPatient" not in ds or "ImageOrientationPatient" not in ds:
        return "no ImagePositionPatient/ImageOrientationPatient"
    try:
        position, orientation = _position(ds), _orientation(ds)
    except (TypeError, ValueError):
        return "position or orientation values that are not numbers"
    if position.shape != (3,) or orientation.shape != (6,):
        return f"{position.size} position and {orientation.size} orientation values, not 3 and 6"
    if not (np.isfinite(position).all() and np.isfinite(orientation).all()):
        return "position or orientation values that are NaN or infinite"
    if np.abs(position).max() > MAX_MM or np.abs(orientation).max() > MAX_MM:
        return "position or orientation values beyond 1000 km"
    try:
        slices.slice_normal(orientation)
    except ValueError:
        return "row and column directions that are parallel or zero"
    return ""


def _need_two(path: Path, count: int, qualifier: str) -> None:
    if count < 2:
        raise UnreadableVolume(
            f"{path.name}: the series has only {count} slice{qualifier}; a surface needs at "
            "least 2 slices. Pass the folder (or a .zip of it) that holds the whole series."
        )


def _decode(
    path: Path, entries: list[Entry], notes: list[str]
) -> tuple[list[np.ndarray], list[tuple[float, float]]]:
    """Pixel arrays (rows, columns) and (slope, intercept) per slice, in the given order."""
    pixels, scales = [], []
    for array, scale in _decoded(path, entries, notes):
        pixels.append(array)
        scales.append(scale)
    return pixels, scales


def _decoded(
    path: Path, entries: list[Entry], notes: list[str]
) -> Iterator[tuple[np.ndarray, tuple[float, float]]]:
    """Each slice's pixel array (rows, columns) and (slope, intercept), one at a time."""
    with recorded_warnings("pydicom") as caught:
        for entry in entries:
            try:
                ds = read_dataset(entry)
                array = ds.pixel_array
            except MissError:
                raise
            except Exception as exc:
                raise _undecodable(path, entry, exc) from exc
            if array.ndim != 2:
                raise UnreadableVolume(
                    f"{path.name}: {entry.label} has pixel shape {array.shape}; only "
                    "single-channel (greyscale) slices can be stacked: export the series as "
                    "MONOCHROME2, one frame per file."
                )
            yield array, _rescale(path, entry, ds)
    notes.extend(caught)


def _rescale(path: Path, entry: Entry, ds: Dataset) -> tuple[float, float]:
    """(RescaleSlope, RescaleIntercept); absent, empty or 0 slope mean (1, 0)."""
    try:
        slope = float(ds.get("RescaleSlope", 1) or 1)
        intercept = float(ds.get("RescaleIntercept", 0) or 0)
    except (TypeError, ValueError) as exc:
        raise UnreadableVolume(
            f"{path.name}: {entry.label} has a RescaleSlope/RescaleIntercept that is not a number "
            f"({exc}); fix or remove those tags."
        ) from exc
    if not (np.isfinite(slope) and np.isfinite(intercept)):
        raise UnreadableVolume(
            f"{path.name}: {entry.label} has RescaleSlope {slope} and RescaleIntercept "
            f"{intercept}; they must be finite numbers: fix or remove those tags."
        )
    return slope, intercept


def _undecodable(path: Path, entry: Entry, exc: Exception) -> UnreadableVolume:
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    # Decoder plug-ins name their input by repr ("<_io.BytesIO object at 0x7f...>").
    text = re.sub(r"<[^<>]* at 0x[0-9a-fA-F]+>", "the data", " ".join(lines))[:300]
    text = text or "the decoder gave no reason"
    lower = text.lower()
    fix = "The file may be truncated or damaged; copy it again."
    if "missing dependencies" in lower or "no pixel data decoders" in lower:
        fix = "Its compression needs a pixel decoder: install pylibjpeg with its openjpeg/libjpeg/rle plug-ins."
    elif "no 'pixel data'" in lower:
        fix = "It holds no image: remove it from the folder, or export the series again."
    elif "plugins" in lower:
        fix = "Its compressed pixel data is damaged; export the series again (uncompressed if possible)."
    return UnreadableVolume(
        f"{path.name}: cannot decode the pixels of {entry.label} ({text}). {fix}"
    )


#: The note a series whose slices rescale differently gets.
RESCALED_APART = "rescale slope/intercept differ between slices; each slice rescaled on its own"


def rescaled_stack(
    pixels: list[np.ndarray], scales: list[tuple[float, float]], notes: list[str]
) -> tuple[np.ndarray, tuple[float, float]]:
    """Apply RescaleSlope/Intercept and stack into a C-ordered (Z, Y, X) array.

    Integer slope and intercept shared by all slices give int16 (or int32 when the
    range needs it); anything else gives float32.

    Returns
    -------
    stack : (Z, Y, X) array in real units (HU for CT)
    rescale : (slope, intercept) of the first slice
    """
    integer = all(p.dtype.kind in "iub" for p in pixels)
    raw = (
        (min(int(p.min()) for p in pixels), max(int(p.max()) for p in pixels))
        if integer
        else (0, 0)
    )
    dtype, uniform = _stack_dtype(scales, raw, integer)
    stack = np.zeros((len(pixels),) + pixels[0].shape, dtype=dtype)
    for k, (array, scale) in enumerate(zip(pixels, scales, strict=True)):
        stack[k] = _rescaled(array, scale, dtype)
    if not uniform:
        notes.append(RESCALED_APART)
    return stack, scales[0]


def _stack_dtype(
    scales: list[tuple[float, float]], raw: tuple[int, int], integer: bool
) -> tuple[np.dtype, bool]:
    """The stack's dtype (and whether every slice rescales alike) from the slices'
    (slope, intercept), their raw value range and whether all their pixels are integers."""
    slope, intercept = scales[0]
    uniform = all(s == scales[0] for s in scales)
    # Exact integers only where int64 cannot overflow: integer pixels, modest slope.
    integral = (
        uniform
        and integer
        and slope.is_integer()
        and intercept.is_integer()
        and abs(slope) <= 2**16
        and abs(intercept) <= 2**31
    )
    dtype = integer_dtype(raw, slope, intercept) if integral else np.dtype(np.float32)
    return dtype, uniform


def _rescaled(array: np.ndarray, scale: tuple[float, float], dtype: np.dtype) -> np.ndarray:
    """One slice in real units, as ``dtype``."""
    s, b = scale
    if dtype.kind in "iu":  # int64 keeps slope * raw + intercept exact before narrowing
        return (array.astype(np.int64) * int(s) + int(b)).astype(dtype)
    return (array * s + b).astype(dtype)


def _pixel_spacing(ds: Dataset) -> tuple[float, float] | None:
    """(between rows, between columns) in mm; None when absent or not two positive numbers."""
    value = ds.get("PixelSpacing") or ds.get("ImagerPixelSpacing")
    try:
        spacing = np.asarray(value, float).ravel() if value is not None else np.zeros(0)
    except (TypeError, ValueError):
        return None
    if spacing.shape != (2,) or not (np.isfinite(spacing).all() and (spacing > 0).all()):
        return None
    return float(spacing[0]), float(spacing[1])


def _affine(
    ds: Dataset, origin: np.ndarray, step: np.ndarray, normal: np.ndarray, notes: list[str]
) -> np.ndarray:
    """Voxel (i, j, k) to LPS mm: in-plane from IOP and PixelSpacing, k from the slice step."""
    iop = _orientation(ds)
    spacing = _pixel_spacing(ds)
    if spacing is None:
        notes.append("no usable PixelSpacing: assumed 1 mm pixels")
        spacing = (1.0, 1.0)
    affine = np.eye(4)
    # PixelSpacing is (between rows, between columns); i runs along a row.
    affine[:3, 0] = iop[:3] * float(spacing[1])
    affine[:3, 1] = iop[3:6] * float(spacing[0])
    affine[:3, 2] = step
    affine[:3, 3] = origin
    tilt = np.degrees(np.arccos(np.clip(abs(step @ normal) / np.linalg.norm(step), 0.0, 1.0)))
    if tilt > 0.1:
        notes.append(
            f"gantry tilt: slices step {tilt:.1f} deg off their normal; the affine is sheared "
            "(slices are not resampled in-plane)"
        )
    return affine
