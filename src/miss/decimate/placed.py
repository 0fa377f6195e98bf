"""Edge collapse with the surviving vertex placed by the quadric, within a proven bound: the
native kernel of ``_placed.cpp`` (a C++ extension built at install, setup.py), called
through ctypes, which lets go of the GIL for the call.

Unlike vertex removal (schroeder) and the half-edge collapse (:mod:`miss.decimate.collapse`),
it moves vertices: each collapse puts the vertex that stays where the input's planes around
both ends meet best (Garland and Heckbert's quadric), so a noisy surface is followed by fewer,
better placed vertices. Its bound is the overlay bound of vertex removal carried over to the
two fans of an edge, and what each triangle has spent is a box of error vectors, grown at
each collapse by the signed height differences along the patch's normal, so that a lift and
a later drop cancel (see the kernel's header): every output point is within the bound of the
input surface and every input point within it of the output, however the collapses chain.

Vertices on a boundary (an open fan) are neither moved nor removed (schroeder and the
half-edge collapse do remove them along the boundary); locked vertices are not moved nor
removed either, but may take in a free neighbour. The output's vertex array is the input's
with the survivors moved (the faces index it), so that a caller keeps its vertex numbering
(the locks of a job's blocks).
"""

from __future__ import annotations

import ctypes
import importlib
import math
from functools import cache

import numpy as np

from miss._process import usable_cores
from miss.decimate._fan import slabs
from miss.decimate.collapse import _slab_count
from miss.types import Mesh

#: Stages of a run, as fractions of its bound (see :data:`miss.decimate.collapse.STAGES`).
STAGES: tuple[float, ...] = (0.5, 1.0)
# The most triangles a vertex may carry after a collapse (vertex removal's is 32): on CThead
# bone at 0.002, 16 kept 105 436 triangles against 105 444 with 32, and the table is half.
_VALENCE_CAP = 16

#: What a run did, in the order :func:`placed` fills ``counts``.
COUNTS = (
    "vertices tried",
    "put back at their cost",
    "overlays weighed",
    "collapsed to the quadric's point",
    "collapsed to the kept end",
    "collapsed to the other end",
)

_P, _I, _D, _C = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double, ctypes.c_int


@cache
def _library() -> ctypes.CDLL | None:
    """The built kernel, or None where the extension is not there or does not load."""
    try:
        module = importlib.import_module("miss.decimate._placed")
        lib = ctypes.CDLL(module.__file__)
        fn = lib.miss_placed_collapse
        # pts, n_pts, faces, n_faces, alive, locked, cap, stages, n_stages, bound, slack,
        # target, slab, count, threads, out_alive, out_bound, counts
        fn.argtypes = [_P, _I, _P, _I, _P, _P, _C, _P, _C, _D, _D, _I, _P, _C, _C, _P, _P, _P]
        fn.restype = ctypes.c_int
    except (ImportError, OSError, AttributeError):
        return None
    return lib


def native() -> bool:
    """Whether the kernel was built here."""
    return _library() is not None


def placed(
    mesh: Mesh,
    reduce: float,
    bound_mm: float,
    locked: np.ndarray | None = None,
    stages: tuple[float, ...] = STAGES,
    counts: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, float]:
    """(vertices, faces kept, the bound of the last stage run in mm).

    ``vertices`` is (N, 3) float64, the input's with the collapses' survivors moved; the faces
    index it. ``reduce``, ``bound_mm``, ``locked`` and ``stages`` are as
    :func:`miss.decimate.collapse.collapse`'s. ``counts``, (6,) int64, is filled with
    what the run did (:data:`COUNTS`). Raises MemoryError where the kernel ran out of
    memory, RuntimeError where it was not built (see :func:`native`).
    """
    lib = _library()
    if lib is None:
        raise RuntimeError(
            "the placed collapse was not built: run `make test` (needs a C++ compiler)"
        )
    pts = np.array(mesh.vertices, dtype=np.float64, order="C")  # a copy: moved in place
    work = np.array(mesh.faces, dtype=np.int32, order="C")
    free = np.zeros(len(pts), np.uint8) if locked is None else locked.astype(np.uint8)
    free = np.ascontiguousarray(free)
    alive = np.zeros(len(work), np.uint8)
    target = math.floor(len(work) * (1.0 - reduce) + 1e-9)
    share = np.ascontiguousarray(stages, dtype=np.float64)
    slack = 1e-12 * mesh.diagonal()  # distances within round-off of zero count as zero
    # the slabs of a large mesh, run side by side (as the half-edge collapse's): how many
    # is set by the mesh, not the machine, so that the output is the same anywhere
    count = _slab_count(len(work))
    slab = slabs(pts, work, count) if count > 1 else np.zeros(len(pts), np.int32)
    slab = np.ascontiguousarray(slab, dtype=np.int32)
    left, ended = ctypes.c_int64(0), ctypes.c_double(0.0)
    did = np.zeros(len(COUNTS), np.int64) if counts is None else counts
    failed = lib.miss_placed_collapse(
        pts.ctypes.data, len(pts), work.ctypes.data, len(work), alive.ctypes.data,
        free.ctypes.data, _VALENCE_CAP, share.ctypes.data, len(share), bound_mm, slack,
        target, slab.ctypes.data, count, usable_cores(), ctypes.byref(left),
        ctypes.byref(ended), did.ctypes.data,
    )  # fmt: skip
    if failed:
        raise MemoryError("out of memory in the placed collapse")
    return pts, work[alive.view(bool)], ended.value
