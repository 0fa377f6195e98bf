"""The two values that travel through MISS: a ``Volume`` in and a ``Mesh`` out.

Coordinates inside MISS are patient LPS millimetres (DICOM convention: +x to the
patient's Left, +y Posterior, +z Superior).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from miss.errors import BadParameter


def column_bounds(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column minimum and maximum of an (N, K) array, in its own dtype.

    Column by column: numpy's ``min(axis=0)`` over a tall, narrow array walks it with a
    stride and is 20x slower (20 ms against 1 ms for 400 k points here).
    """
    columns = range(values.shape[1])
    lo = np.array([values[:, k].min() for k in columns], dtype=values.dtype)
    hi = np.array([values[:, k].max() for k in columns], dtype=values.dtype)
    return lo, hi


@dataclass(frozen=True)
class Volume:
    """A scalar volume on a (possibly sheared) regular grid.

    Attributes
    ----------
    data : (X, Y, Z) array
        Voxel values in real units (HU for CT after rescale), indexed
        ``data[i, j, k]`` with i = column, j = row, k = slice. Readers return it
        Fortran-ordered (i fastest) when they can, so VTK takes it without a copy.
    affine : (4, 4) float64 array
        Maps voxel indices ``(i, j, k, 1)`` to LPS millimetres. Columns 0-2 are the
        step vectors along i, j, k; a gantry tilt makes column 2 oblique (sheared grid).
    meta : dict
        Non-identifying metadata: ``modality``, ``units`` ("HU" or "" when unknown),
        ``rescale`` (slope, intercept), ``series_description``, ``series_uid``,
        ``series`` (list of series found beside it), ``source_format``, ``notes``.
    patient : dict
        Patient-identifying fields (name, id, birth date ...), kept apart so that
        sharing can strip them in one place.
    """

    data: np.ndarray
    affine: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)
    patient: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.data.ndim != 3:
            raise ValueError(f"Volume data must be 3-D, got shape {self.data.shape}.")
        aff = np.asarray(self.affine, dtype=np.float64)
        if aff.shape != (4, 4):
            raise ValueError(f"Volume affine must be 4x4, got {aff.shape}.")
        object.__setattr__(self, "affine", aff)

    @property
    def dims(self) -> tuple[int, int, int]:
        """Voxel counts (x, y, z) = (columns, rows, slices)."""
        x, y, z = self.data.shape
        return int(x), int(y), int(z)

    @property
    def spacing(self) -> tuple[float, float, float]:
        """Step length in mm along each voxel axis (norms of the affine's columns)."""
        s = np.linalg.norm(self.affine[:3, :3], axis=0)
        return float(s[0]), float(s[1]), float(s[2])

    def value_range(self) -> tuple[float, float]:
        """(min, max) of the voxel values, in the volume's real units."""
        return float(np.nanmin(self.data)), float(np.nanmax(self.data))


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh in LPS millimetres.

    Attributes
    ----------
    vertices : (N, 3) float32 array, mm
    faces : (F, 3) int32 array
        Counter-clockwise seen from outside (normals point out of the structure).
    normals : (N, 3) float32 array or None
        Unit per-vertex normals pointing outward.
    labels : (F,) int array or None
        Optional per-face structure label.
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    labels: np.ndarray | None = None

    @property
    def n_vertices(self) -> int:
        """Vertices (N)."""
        return int(self.vertices.shape[0])

    @property
    def n_triangles(self) -> int:
        """Triangles (F)."""
        return int(self.faces.shape[0])

    def bounds(self) -> np.ndarray:
        """(2, 3) array: min and max corner in mm."""
        if self.n_vertices == 0:
            return np.zeros((2, 3))
        return np.stack(column_bounds(self.vertices))

    def diagonal(self) -> float:
        """Length of the bounding-box diagonal in mm."""
        lo, hi = self.bounds()
        return float(np.linalg.norm(hi - lo))


#: The environment variable that sets :func:`memory_budget`, MB. The server's setting of
#: the same name (default 1024) says which stored volumes it reads whole; a job still
#: meshes one over this budget block by block, whatever read it.
IN_MEMORY_ENV = "MISS_IN_MEMORY_MAX_MB"
#: :func:`memory_budget` when the variable is unset, MB. A job whose voxels fit meshes them
#: in one pass and needs about 4 times them at its peak (the volume, VTK's working arrays,
#: the mesh: 296 MB of voxels took 1.18 GB over ``miss convert``'s baseline); larger
#: volumes are read to disk and meshed block by block, in 0.6-0.85 GB up to 1.18 GB of
#: voxels (``benchmarks/big_volume.py``). 256 MB keeps either way near 1 GB.
IN_MEMORY_MAX_MB = 256.0


def memory_budget() -> int:
    """Bytes of voxels a job reads whole into memory and meshes in one pass
    (``MISS_IN_MEMORY_MAX_MB``, default :data:`IN_MEMORY_MAX_MB`); a volume over it is
    read to a chunked array on disk and meshed block by block."""
    text = os.environ.get(IN_MEMORY_ENV, "").strip()
    if not text:
        return int(IN_MEMORY_MAX_MB * 2**20)
    try:
        megabytes = float(text)
    except ValueError:
        megabytes = -1.0
    if not megabytes >= 0:  # NaN too
        raise BadParameter(
            f"{IN_MEMORY_ENV} must be a number of MB (0 or more), got {text!r}; e.g. "
            f"{IN_MEMORY_ENV}=1024."
        )
    return int(megabytes * 2**20)


def in_memory(volume: Volume) -> Volume:
    """``volume`` with its voxels read into one (X, Y, Z) numpy array when they are on
    disk (a :class:`StridedView` or a stored array), for the work not yet done block by
    block (label maps). A worker's memory cap stops a region too large for it."""
    if isinstance(volume.data, np.ndarray):
        return volume
    data = np.asfortranarray(volume.data[(slice(None),) * 3])
    return replace(volume, data=data)


class StridedView:
    """A lazy box of a 3-D array at a sample step: slicing it (unit steps) reads only that
    part of ``data``. What :meth:`miss.spec.Region.apply` returns for data on disk."""

    def __init__(self, data: Any, box: Sequence[tuple[int, int]], steps: Sequence[int]):
        self.data, self.box, self.steps = data, tuple(box), tuple(steps)
        self.shape = tuple(
            len(range(lo, hi + 1, st)) for (lo, hi), st in zip(self.box, self.steps, strict=True)
        )
        self.dtype = np.dtype(data.dtype)
        self.ndim = 3

    def __getitem__(self, key: tuple[slice, ...]) -> np.ndarray:
        picked = []
        for sl, (lo, _), st, n in zip(key, self.box, self.steps, self.shape, strict=True):
            a, b, step = sl.indices(n)
            picked.append(slice(lo + a * st, lo + (b - 1) * st + 1, st * step))
        return np.asarray(self.data[tuple(picked)])
