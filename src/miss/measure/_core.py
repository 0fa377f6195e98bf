"""What a measurement is, whichever kernels run it: :func:`measure` takes the kernels
(numba's, :mod:`miss.measure._jit`, or the native ones, :mod:`miss.measure._native`), the
same figures either way."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from miss.types import Mesh, column_bounds


@dataclass(frozen=True)
class Deviation:
    """Two-sided distance between surfaces A and B, mm."""

    max_mm: float
    mean_mm: float
    samples: int


@dataclass(frozen=True)
class Side:
    """Surface ``a``'s half of a :func:`deviation`, made before ``b`` exists (e.g. while
    ``b`` is being decimated from it): its sample points, its grid, and the random state
    that ``b``'s sampling goes on from, so that the figures are the same."""

    points: np.ndarray
    grid: tuple
    state: Mapping[str, Any]  # numpy's bit generator state


def grid_shape(verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Origin, cell size (mm) and cell counts of a uniform grid over the mesh's bounding box.

    Cells about the median edge hold a few triangles each; the floor on the size keeps the
    number of cells within about four times the number of triangles whatever the mesh's shape.
    """
    lo, hi = (b.astype(np.float64) for b in column_bounds(verts))
    some = faces[:: max(1, len(faces) // 20_000)]  # a median needs no million edges
    edge = np.linalg.norm(verts[some[:, 0]].astype(np.float64) - verts[some[:, 1]], axis=1)
    extent = np.maximum(hi - lo, 1e-9)
    floor = float(np.prod(extent) / max(4 * len(faces), 1)) ** (1 / 3)
    cell = max(_median(edge), floor, 1e-9)
    dims = np.maximum(np.ceil(extent / cell).astype(np.int64), 1)
    return lo, cell, dims


def _median(values: np.ndarray) -> float:
    """``np.median(values)`` to the bit, without its first call's import of ``numpy.ma``
    (15-18 ms of a fresh process, in which nothing else imports it)."""
    n = len(values)
    if n == 0:
        return math.nan
    half = n // 2
    if n % 2:
        return float(np.partition(values, half)[half])
    part = np.partition(values, [half - 1, half])
    return float((part[half - 1] + part[half]) / 2)


@dataclass(frozen=True)
class Kernels:
    """What a measurement runs: ``sample(mesh, count, rng)`` (the points, corners in vertex
    order and the others in triangle order), ``grid(mesh)`` (its cells) and
    ``search(points, grid, ordered)`` (each point's exact distance): the native ones
    (:data:`NATIVE`) or numba's (:mod:`miss.measure._jit`), the same figures either way."""

    sample: Callable[[Mesh, int, np.random.Generator], np.ndarray]
    grid: Callable[[Mesh], tuple]
    search: Callable[[np.ndarray, tuple, bool], np.ndarray]


def half(a: Mesh, samples: int, seed: int, kernels: Kernels) -> Side:
    """``a``'s :class:`Side` with ``kernels``."""
    rng = np.random.default_rng(seed)
    points = kernels.sample(a, samples, rng)
    return Side(points, kernels.grid(a), rng.bit_generator.state)


def measure(
    a: Mesh, b: Mesh, samples: int, seed: int, side: Side | None, kernels: Kernels
) -> Deviation:
    """:func:`deviation` with ``kernels``."""
    if a.n_triangles == 0 or b.n_triangles == 0:
        return Deviation(0.0, 0.0, 0)
    with ThreadPoolExecutor(max_workers=1) as pool:
        if side is None:
            rng = np.random.default_rng(seed)
            # a's cells (a is the larger surface, as a rule) are made on the second core
            # while this one samples both and makes b's; the searches, on both cores, after
            making = pool.submit(kernels.grid, a)
            points_a = kernels.sample(a, samples, rng)
            points_b = kernels.sample(b, samples, rng)
            grid_a, grid_b = making.result(), kernels.grid(b)
        else:
            rng = np.random.default_rng()
            rng.bit_generator.state = side.state
            making = pool.submit(kernels.grid, b)  # b's cells on the second core meanwhile
            points_b = kernels.sample(b, samples, rng)
            points_a, grid_a, grid_b = side.points, side.grid, making.result()
    # a's points come in a's own order (corners by vertex, the others by triangle): for an
    # extracted surface, neighbours together, searched as they come (a fifth faster on
    # CThead than sorting them by cell first); b's (a decimation's order) are sorted
    d_ab = kernels.search(points_a, grid_b, True)
    both = np.concatenate([d_ab, kernels.search(points_b, grid_a, False)])
    return Deviation(max_mm=float(both.max()), mean_mm=float(both.mean()), samples=len(both))
