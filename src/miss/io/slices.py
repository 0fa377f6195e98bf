"""Geometry of a stack of 2-D slices: order, duplicates, spacing, tilt.

Pure numpy, independent of DICOM, so it can be tested on synthetic stacks.

Slices are placed by their origin (the centre of their first pixel, mm) and ordered by
``d``, the origin's distance along the slice normal. Under a gantry tilt the origins
step obliquely to the normal; the stack is then kept sheared (column 2 of the affine is
the oblique step between origins) rather than resampled in-plane, because resampling
would blur every slice to fix a shape that the sheared affine already describes exactly.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Positions closer than this (mm) along the normal count as the same slice.
DUPLICATE_MM = 0.01
#: Gaps that differ by less than this fraction of the median gap count as even.
EVEN_TOLERANCE = 0.01
#: Uneven stacks are resampled to at most this many times the original slice count.
MAX_UPSAMPLING = 4
#: No scan is longer than this (mm): a stack spanning more has a broken position.
MAX_SPAN_MM = 5000.0


@dataclass(frozen=True)
class Grid:
    """Where the output slices lie.

    Attributes
    ----------
    positions : (K,) float array, mm
        Output slice positions along the normal, first and last equal to the input's.
    step : (3,) float array, mm
        LPS step between consecutive output slice origins (oblique under gantry tilt).
    resampled : bool
        True when ``positions`` differ from the input positions (uneven gaps).
    notes : list of str
    """

    positions: np.ndarray
    step: np.ndarray
    resampled: bool
    notes: list[str] = field(default_factory=list)


def slice_normal(orientation: np.ndarray) -> np.ndarray:
    """Unit normal (3,) of a slice from its 6 direction cosines (row then column, LPS)."""
    row, col = np.asarray(orientation[:3], float), np.asarray(orientation[3:6], float)
    normal = np.cross(row, col)
    length = np.linalg.norm(normal)
    if length < 1e-6:
        raise ValueError(f"row and column directions {row} and {col} are parallel")
    return normal / length


def order_along(origins: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sort slices by position along the normal.

    Parameters
    ----------
    origins : (N, 3) float array, mm
    normal : (3,) unit vector

    Returns
    -------
    order : (N,) int array, indices into ``origins`` from lowest to highest position
    positions : (N,) float array, mm, the sorted positions
    """
    d = np.asarray(origins, float) @ normal
    order = np.argsort(d, kind="stable")
    return order, d[order]


def duplicate_mask(positions: np.ndarray) -> np.ndarray:
    """(N,) bool, True for a sorted slice lying on top of the one kept before it."""
    dup = np.zeros(len(positions), dtype=bool)
    dup[1:] = np.diff(positions) < DUPLICATE_MM
    return dup


def plan_grid(positions: np.ndarray, origins: np.ndarray) -> Grid:
    """Choose the output slice positions for sorted, de-duplicated slices.

    Even gaps keep the slices as they are. Uneven gaps get a regular grid whose step
    is the smallest gap, or the median gap when the smallest would multiply the slice
    count by more than ``MAX_UPSAMPLING``; the step is shrunk slightly so that the grid
    ends exactly on the last slice.

    Parameters
    ----------
    positions : (N,) float array, mm, increasing
    origins : (N, 3) float array, mm, in the same order
    """
    gaps = np.diff(positions)
    span = positions[-1] - positions[0]
    if span > MAX_SPAN_MM:
        raise ValueError(
            f"the slices span {span:.0f} mm (gaps {gaps.min():.2f} to {gaps.max():.0f} mm), more "
            f"than any scan ({MAX_SPAN_MM:.0f} mm): some ImagePositionPatient values are wrong"
        )
    per_mm = (origins[-1] - origins[0]) / span
    notes = _collinearity_notes(positions, origins, per_mm)
    median = float(np.median(gaps))
    if np.ptp(gaps) <= EVEN_TOLERANCE * median:
        return Grid(positions, per_mm * span / (len(positions) - 1), False, notes)
    target, why = float(gaps.min()), "the smallest gap"
    cap = MAX_UPSAMPLING * len(positions)
    if _count(span, target) > cap:
        target, why = median, f"the median gap (the smallest would exceed {MAX_UPSAMPLING}x)"
    count = _count(span, target)
    if count > cap:  # a few huge gaps among small ones: bound the memory, say so
        count, why = cap, f"{MAX_UPSAMPLING}x the slice count (the median gap would need {count})"
    grid = np.linspace(positions[0], positions[-1], count)
    step = span / (count - 1)
    notes.append(
        f"uneven slice gaps ({gaps.min():.2f}-{gaps.max():.2f} mm): resampled {len(positions)} "
        f"slices onto {count} slices {step:.3f} mm apart along the slice normal "
        f"({why}), by linear interpolation between neighbouring slices"
    )
    return Grid(grid, per_mm * step, True, notes)


def _count(span: float, target: float) -> int:
    """Slices on a grid spanning ``span`` mm with steps no longer than ``target`` mm."""
    return int(np.ceil(span / target - 1e-6)) + 1


def _collinearity_notes(
    positions: np.ndarray, origins: np.ndarray, per_mm: np.ndarray
) -> list[str]:
    """Warn when slice origins do not lie on one line (the affine cannot be exact then)."""
    expected = origins[0] + np.outer(positions - positions[0], per_mm)
    worst = float(np.linalg.norm(origins - expected, axis=1).max())
    if worst < 0.1:
        return []
    return [
        f"slice origins stray up to {worst:.2f} mm from a straight line; the affine assumes one"
    ]


def resample(stack: np.ndarray, positions: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Linearly interpolate slices onto new positions along the normal.

    Parameters
    ----------
    stack : (N, Y, X) array
        Slices in position order.
    positions : (N,) float array, mm, increasing
    grid : (K,) float array, mm, within ``[positions[0], positions[-1]]``

    Returns
    -------
    (K, Y, X) float32 array, C-ordered
    """
    out = np.zeros((len(grid),) + stack.shape[1:], dtype=np.float32)
    below = np.clip(np.searchsorted(positions, grid, side="right") - 1, 0, len(positions) - 2)
    weight = (grid - positions[below]) / (positions[below + 1] - positions[below])
    # One output slice at a time keeps the temporaries at the size of one slice.
    for k, (i, w) in enumerate(zip(below, np.clip(weight, 0.0, 1.0), strict=True)):
        out[k] = (1.0 - w) * stack[i] + w * stack[i + 1]
    return out
