"""The sampled measurement of a decimation, in native code: no numba to start.

:func:`deviation` and :func:`side_of` are :mod:`miss.measure._jit`'s, with the same samples,
grid and search, and the same figures to the bit (tests/test_measuring.py), run by the
kernels of ``_nearest.cpp``: a C++ extension built at install (setup.py), called through
ctypes, which lets go of the GIL for each call. The queries run on every core the process
may use, as numba's ``prange`` did.

A process that measures needs numba then only for what else it does. For ``miss convert
--measure`` under the paper's schedule that is nothing: numba's start (0.6-0.9 s on the
2-core test machine), which a measuring process of its own takes on the other core where
the extension is missing (:mod:`miss.measure.measurer`), is not paid at all.

Where numba is loaded already (a server's warmed-up worker), both functions are numba's:
its kernels, compiled for the very CPU they run on, searched 10-20 % faster than these
(the same counts of cells, boxes and triangles per query; ``benchmarks/measure.py``). The
grids are the same, so a half made before numba loaded is still used after. Where the
extension was not built (no C++ compiler at install), :func:`native` says so and both
functions are numba's.
"""

from __future__ import annotations

import ctypes
import importlib
import math
from functools import cache
from typing import Any

import numpy as np

from miss._process import usable_cores
from miss.measure._core import Deviation, Kernels, Side, grid_shape, half, measure
from miss.types import Mesh

_P, _I, _D, _C = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double, ctypes.c_int
_SIGNATURES: dict[str, list[Any]] = {
    "miss_used": [_P, _I, _P],
    "miss_increasing": [_P, _I, _D, _P],
}
for _t in ("f32", "f64"):
    _SIGNATURES |= {
        f"miss_corners_{_t}": [_P, _P, _I, _P],
        f"miss_grid_cells_{_t}": [_P, _I, _P, _D, _P, _P, _P],
        f"miss_cumulative_areas_{_t}": [_P, _P, _I, _P],
        f"miss_inner_points_{_t}": [_P, _P, _P, _I, _P, _P, _P, _P, _P, _I, _P],
        # points, n, lo, cell, dims, offsets, items, rows, cap2, ordered, threads, out
        f"miss_distances_{_t}": [_P, _I, _P, _D, *[_P] * 4, _D, _C, _C, _P],
    }


_ALLOCATING = ("miss_increasing", "miss_grid_cells_", "miss_distances_")


def _checked(failed: int) -> None:
    """A MemoryError where a kernel ran out of memory (as numpy's would raise)."""
    if failed:
        raise MemoryError("out of memory in the measurement's native kernels")


@cache
def _library() -> ctypes.CDLL | None:
    """The built kernels, or None where the extension is not there or does not load."""
    try:
        # by name: a compiled module, absent where nothing built it
        nearest = importlib.import_module("miss.measure._nearest")
        lib = ctypes.CDLL(nearest.__file__)
        for name, args in _SIGNATURES.items():
            getattr(lib, name).argtypes = args
            # those that allocate answer 1 where they ran out of memory (see _checked)
            getattr(lib, name).restype = ctypes.c_int if name.startswith(_ALLOCATING) else None
    except (ImportError, OSError, AttributeError):
        return None
    return lib


def native() -> bool:
    """Whether the native kernels are built here (else :func:`deviation` is numba's)."""
    return _library() is not None


def native_side_of(a: Mesh, samples: int = 100_000, seed: int = 0) -> Side:
    """:func:`side_of` with the native kernels, wherever numba is."""
    return half(a, samples, seed, NATIVE)


def native_deviation(
    a: Mesh, b: Mesh, samples: int = 100_000, seed: int = 0, side: Side | None = None
) -> Deviation:
    """:func:`deviation` with the native kernels, wherever numba is (``side``: made by
    either)."""
    return measure(a, b, samples, seed, side, NATIVE)


def _arrays(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, str]:
    """The mesh's vertices (float32 or float64, as they are) and int32 faces, contiguous,
    and the kernels' suffix for that vertex type."""
    verts = np.ascontiguousarray(mesh.vertices)
    if verts.dtype not in (np.float32, np.float64):
        verts = verts.astype(np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int32)
    return verts, faces, "f32" if verts.dtype == np.float32 else "f64"


def _sample(mesh: Mesh, count: int, rng: np.random.Generator) -> np.ndarray:
    """:func:`miss.measure._jit.sample_surface`'s points, its corners in vertex order and its
    inner points in triangle order (``miss.measure._jit._sample`` not ``drawn``)."""
    lib = _library()
    assert lib is not None
    verts, faces, t = _arrays(mesh)
    mask = np.zeros(len(verts), dtype=np.uint8)
    lib.miss_used(faces.ctypes.data, len(faces), mask.ctypes.data)
    used = np.flatnonzero(mask)
    chosen = rng.choice(len(used), size=min(len(used), count // 2), replace=False)
    mark = np.zeros(len(used), dtype=bool)  # the same vertices in increasing order
    mark[chosen] = True
    corners = verts[used[np.flatnonzero(mark)]]
    n_inner = count - len(corners)
    cum = np.empty(len(faces))
    getattr(lib, f"miss_cumulative_areas_{t}")(
        verts.ctypes.data, faces.ctypes.data, len(faces), cum.ctypes.data
    )
    target = rng.random(n_inner) * cum[-1]
    order = np.empty(n_inner, dtype=np.int64)
    _checked(lib.miss_increasing(target.ctypes.data, n_inner, float(cum[-1]), order.ctypes.data))
    r1, r2 = rng.random(n_inner), rng.random(n_inner)
    out = np.empty((count, 3))
    out[: len(corners)] = corners
    slots = np.arange(n_inner, dtype=np.int64)
    inner = out[len(corners) :]
    getattr(lib, f"miss_inner_points_{t}")(
        verts.ctypes.data, faces.ctypes.data, cum.ctypes.data, len(cum), target.ctypes.data,
        order.ctypes.data, r1.ctypes.data, r2.ctypes.data, slots.ctypes.data, n_inner,
        inner.ctypes.data,
    )  # fmt: skip
    return out


def native_grid(mesh: Mesh) -> tuple:
    """The cells of ``mesh``'s triangles, :func:`miss.measure._jit.jit_grid`'s (origin,
    cell size, counts, CSR offsets and items, each triangle's corners in a row)."""
    lib = _library()
    assert lib is not None
    verts, faces, t = _arrays(mesh)
    lo, cell, dims = grid_shape(verts, faces)
    dims = np.ascontiguousarray(dims, dtype=np.int64)
    tri = np.empty((len(faces), 9), dtype=verts.dtype)
    getattr(lib, f"miss_corners_{t}")(
        verts.ctypes.data, faces.ctypes.data, len(faces), tri.ctypes.data
    )
    cells = getattr(lib, f"miss_grid_cells_{t}")
    offsets = np.zeros(int(np.prod(dims)) + 1, dtype=np.int32)
    where = (
        tri.ctypes.data,
        len(faces),
        lo.ctypes.data,
        cell,
        dims.ctypes.data,
        offsets.ctypes.data,
    )
    _checked(cells(*where, None))  # each cell's count, then their running sum
    items = np.empty(int(offsets[-1]), dtype=np.int32)
    _checked(cells(*where, items.ctypes.data))
    return (lo, cell, dims, offsets, items, tri)


def distances(
    points: np.ndarray, grid: tuple, cap: float = math.inf, ordered: bool = False
) -> np.ndarray:
    """Exact distance (mm) from each of (P, 3) points to the nearest triangle of ``grid``'s
    surface (:func:`native_grid`), up to ``cap`` (see :func:`miss.measure._jit.distances_to`);
    ``ordered``: searched in the points' own order, else by blocks of cells."""
    lib = _library()
    assert lib is not None
    lo, cell, dims, offsets, items, tri = grid
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.empty(len(pts))
    if len(pts) == 0:
        return out
    search = getattr(lib, "miss_distances_f32" if tri.dtype == np.float32 else "miss_distances_f64")
    failed = search(
        pts.ctypes.data, len(pts), lo.ctypes.data, cell, dims.ctypes.data,
        offsets.ctypes.data, items.ctypes.data, tri.ctypes.data, cap * cap, int(ordered),
        usable_cores(), out.ctypes.data,
    )  # fmt: skip
    _checked(failed)
    return out


#: The native kernels, as :func:`measure` takes them.
NATIVE = Kernels(
    sample=lambda mesh, count, rng: _sample(mesh, count, rng),
    grid=native_grid,
    search=lambda points, grid, ordered: distances(points, grid, ordered=ordered),
)
