"""Stack the slices of one DICOM series into an (X, Y, Z) array and its LPS affine.

Slices are ordered by their position along the slice normal (never by file name or
InstanceNumber), duplicates are dropped, pixel values are rescaled to real units, and
uneven gaps are resampled onto a regular grid (see :mod:`miss.io.slices`).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataset import Dataset

from miss.errors import UnreadableVolume
from miss.io import slices
from miss.io.common import integer_dtype, recorded_warnings, zyx_to_xyz
from miss.io.dicom_files import Entry


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


def assemble(path: Path, files: list[tuple[Entry, Dataset]]) -> Stack:
    """Order, de-duplicate, decode, rescale and (if gaps are uneven) resample a series.

    Parameters
    ----------
    path : Path
        What the user passed (for messages).
    files : list of (Entry, header Dataset)
        The series' files, headers read without pixels, in any order.
    """
    notes: list[str] = []
    files = _placed(path, _consistent(files, notes), notes)
    normal = slices.slice_normal(np.asarray(files[0][1].ImageOrientationPatient, float))
    origins = np.array([np.asarray(ds.ImagePositionPatient, float) for _, ds in files])
    order, positions = slices.order_along(origins, normal)
    duplicate = slices.duplicate_mask(positions)
    if duplicate.any():
        notes.append(f"dropped {int(duplicate.sum())} slice(s) at the same position as another")
    keep, positions = order[~duplicate], positions[~duplicate]
    _need_two(path, len(keep), " at distinct positions")
    pixels, scales = _decode(path, [files[i][0] for i in keep], notes)
    zyx, rescale = rescaled_stack(pixels, scales, notes)
    grid = slices.plan_grid(positions, origins[keep])
    if grid.resampled:
        zyx = slices.resample(zyx, positions, grid.positions)
    affine = _affine(files[keep[0]][1], origins[keep[0]], grid.step, normal, notes)
    return Stack(zyx_to_xyz(zyx), affine, rescale, notes + grid.notes)


def _consistent(
    files: list[tuple[Entry, Dataset]], notes: list[str]
) -> list[tuple[Entry, Dataset]]:
    """Keep the slices sharing the commonest size and orientation (drops scouts mixed in)."""

    def key(ds: Dataset) -> tuple:
        iop = ds.get("ImageOrientationPatient")
        return (
            int(ds.Rows),
            int(ds.Columns),
            None if iop is None else tuple(np.round(np.asarray(iop, float), 3)),
        )

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
    placed = [
        (e, ds)
        for e, ds in files
        if "ImagePositionPatient" in ds and "ImageOrientationPatient" in ds
    ]
    if not placed:
        raise UnreadableVolume(
            f"{path.name}: the slices carry no ImagePositionPatient/ImageOrientationPatient, "
            "so they cannot be stacked in space; export the series with geometry tags."
        )
    if len(placed) < len(files):
        notes.append(f"skipped {len(files) - len(placed)} slice(s) without position or orientation")
    _need_two(path, len(placed), "")
    return placed


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
    with recorded_warnings("pydicom") as caught:
        for entry in entries:
            try:
                ds = pydicom.dcmread(entry.fetch())
                array = ds.pixel_array
            except Exception as exc:
                raise _undecodable(path, entry, exc) from exc
            if array.ndim != 2:
                raise UnreadableVolume(
                    f"{path.name}: {entry.label} has pixel shape {array.shape}; only "
                    "single-channel (greyscale) slices can be stacked."
                )
            pixels.append(array)
            scales.append(
                (float(ds.get("RescaleSlope", 1) or 1), float(ds.get("RescaleIntercept", 0) or 0))
            )
    notes.extend(caught)
    return pixels, scales


def _undecodable(path: Path, entry: Entry, exc: Exception) -> UnreadableVolume:
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    fix = "The file may be truncated or damaged; copy it again."
    if "plugin" in text.lower() or "decod" in text.lower():
        fix = "Its compression needs a pixel decoder: install pylibjpeg with its openjpeg/libjpeg/rle plug-ins."
    return UnreadableVolume(
        f"{path.name}: cannot decode the pixels of {entry.label} ({text}). {fix}"
    )


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
    slope, intercept = scales[0]
    uniform = all(s == scales[0] for s in scales)
    integral = uniform and slope.is_integer() and intercept.is_integer()
    if integral:
        raw = (min(int(p.min()) for p in pixels), max(int(p.max()) for p in pixels))
        dtype = integer_dtype(raw, slope, intercept)
    else:
        dtype = np.dtype(np.float32)
    stack = np.zeros((len(pixels),) + pixels[0].shape, dtype=dtype)
    for k, (array, (s, b)) in enumerate(zip(pixels, scales, strict=True)):
        # int64 keeps slope * raw + intercept exact before the narrowing store.
        stack[k] = array.astype(np.int64) * int(s) + int(b) if integral else array * s + b
    if not uniform:
        notes.append(
            "rescale slope/intercept differ between slices; each slice rescaled on its own"
        )
    return stack, (slope, intercept)


def _affine(
    ds: Dataset, origin: np.ndarray, step: np.ndarray, normal: np.ndarray, notes: list[str]
) -> np.ndarray:
    """Voxel (i, j, k) to LPS mm: in-plane from IOP and PixelSpacing, k from the slice step."""
    iop = np.asarray(ds.ImageOrientationPatient, float)
    spacing = ds.get("PixelSpacing") or ds.get("ImagerPixelSpacing")
    if spacing is None:
        notes.append("no PixelSpacing: assumed 1 mm pixels")
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
