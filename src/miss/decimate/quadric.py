"""meshoptimizer's edge-collapse simplifier with quadric error metrics, in two phases:
slabs simplified on every core with their cut borders locked, then the whole mesh."""

from __future__ import annotations

import ctypes
import itertools
import os
import sys
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import meshoptimizer
import numpy as np

from miss.types import Mesh, column_bounds

# Below this many triangles one meshoptimizer call is fast enough (< 0.1 s) to not split.
_PARALLEL_MIN_TRIANGLES = 200_000
# Slabs for the first, parallel phase; more slabs than cores evens out uneven slabs.
_SLABS = 16
# The parallel phase keeps this multiple of the final share of each slab (and is skipped when
# that would be more than _FIRST_PHASE_MAX_KEEP); the whole mesh is then finished in one
# call, so the seams (locked in the first phase) get simplified like everything else.
_FIRST_PHASE_FACTOR = 2.0
_FIRST_PHASE_MAX_KEEP = 0.6


def _bind_simplify_with_attributes() -> Any:
    """meshoptimizer's C ``meshopt_simplifyWithAttributes`` with its argument types declared.

    The Python wrapper (0.2.x) leaves them undeclared, so ctypes refuses the float error
    and would pass sizes as 32-bit ints; the C signature is declared here once.
    """
    fn = meshoptimizer.simplifier.lib.meshopt_simplifyWithAttributes
    u32, f32, size = ctypes.POINTER(ctypes.c_uint), ctypes.POINTER(ctypes.c_float), ctypes.c_size_t
    fn.argtypes = [u32, u32, size, f32, size, size, f32, size, f32, size,
                   ctypes.POINTER(ctypes.c_ubyte), size, ctypes.c_float, ctypes.c_uint, f32]  # fmt: skip
    fn.restype = size
    return fn


_SIMPLIFY_WITH_LOCKS = _bind_simplify_with_attributes()


def _simplify(
    indices: np.ndarray,
    positions: np.ndarray,
    target: int,
    max_error: float,
    options: int,
    lock: np.ndarray,
) -> tuple[np.ndarray, float]:
    """One meshoptimizer call: (indices kept, its relative error). ctypes releases the GIL.

    indices (3F,) uint32, positions (N, 3) float32, ``lock`` (N,) uint8: vertices that stay.
    """
    out = np.empty_like(indices)
    error = ctypes.c_float(0.0)
    no_weights = np.zeros(1, dtype=np.float32)
    count = _SIMPLIFY_WITH_LOCKS(
        out.ctypes.data_as(ctypes.POINTER(ctypes.c_uint)),
        indices.ctypes.data_as(ctypes.POINTER(ctypes.c_uint)),
        len(indices),
        positions.ctypes.data_as(ctypes.POINTER(ctypes.c_float)),
        len(positions),
        12,
        positions.ctypes.data_as(ctypes.POINTER(ctypes.c_float)),  # no attributes weighed
        12,
        no_weights.ctypes.data_as(ctypes.POINTER(ctypes.c_float)),
        0,
        lock.ctypes.data_as(ctypes.POINTER(ctypes.c_ubyte)),
        max(3, target // 3 * 3),
        float(max_error),
        options,
        ctypes.byref(error),
    )
    return out[:count], float(error.value)


def _slabs(faces: np.ndarray, positions: np.ndarray, count: int) -> list[np.ndarray]:
    """The flat index arrays of ``count`` slabs of triangles with about equal numbers of
    triangles, cut across the mesh's longest axis by triangle centroid."""
    lo, hi = column_bounds(positions)
    axis = int(np.argmax(hi - lo))
    coord = np.ascontiguousarray(positions[:, axis], dtype=np.float64)
    # the cuts from a sample of at most ~64 k triangles: equal enough, and no sort of all
    sample = faces[:: max(1, len(faces) // 65_536)]
    centre = coord[sample[:, 0]] + coord[sample[:, 1]] + coord[sample[:, 2]]
    cuts = np.quantile(centre, np.linspace(0.0, 1.0, count + 1)[1:-1])
    flat, starts = _partition(faces, coord, cuts)
    return [flat[3 * a : 3 * b] for a, b in itertools.pairwise(starts)]


def _partition(
    faces: np.ndarray, coord: np.ndarray, cuts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Faces (F, 3) bucketed by the slab (between ``cuts``) of their centroid's ``coord``:
    flat uint32 indices slab after slab (each slab's faces in their order), and the slabs'
    first faces (len(cuts) + 2). numba's loop (:mod:`miss.decimate._quadric`) when numba is loaded."""
    if "numba" in sys.modules:
        from miss.decimate._quadric import partition

        return partition(faces, coord, cuts)
    centre = coord.take(faces[:, 0]) + coord.take(faces[:, 1]) + coord.take(faces[:, 2])
    slab = np.searchsorted(cuts, centre, side="right").astype(np.uint8)  # _SLABS <= 256
    order = np.argsort(slab, kind="stable")  # a radix sort for bytes
    starts = np.zeros(len(cuts) + 2, dtype=np.int64)
    np.cumsum(np.bincount(slab, minlength=len(cuts) + 1), out=starts[1:])
    return faces.take(order, axis=0).astype(np.uint32).ravel(), starts


def _roots(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(N,) connected-component root of every vertex: its piece's smallest vertex index.

    Union-find in whole-array steps: every triangle hooks the roots of its corners under
    the smallest of them, then paths are halved until every vertex points at a root; a few
    rounds, each on the triangles whose corners still have different roots (int32 and
    column by column, so the work arrays stay a fraction of the mesh). numba's loop
    (:mod:`miss.decimate._quadric`) when numba is loaded already.
    """
    if "numba" in sys.modules:
        from miss.decimate._quadric import roots

        return roots(faces, n_vertices)
    corners = [np.ascontiguousarray(faces[:, k], dtype=np.int32) for k in range(3)]
    parent = np.arange(n_vertices, dtype=np.int32)
    low = np.minimum(np.minimum(corners[0], corners[1]), corners[2])
    while True:
        for corner in corners:
            np.minimum.at(parent, corner, low)
        while not np.array_equal(grand := parent.take(parent), parent):
            parent = grand
        corners = [parent.take(corner) for corner in corners]  # their roots, to hook next
        low = np.minimum(np.minimum(corners[0], corners[1]), corners[2])
        apart = (corners[0] != low) | (corners[1] != low) | (corners[2] != low)
        if not apart.any():
            return parent.astype(np.int64)
        low = np.compress(apart, low)
        corners = [np.compress(apart, corner) for corner in corners]


# Pieces the reduce rate would leave fewer triangles than this are kept whole.
_SMALL_PIECE_TRIANGLES = 8
# Pieces below this size are simplified each on its own, to its own share of the target.
_OWN_TARGET_TRIANGLES = 20_000


def quadric(
    mesh: Mesh, reduce: float, max_error: float, locked: np.ndarray | None = None
) -> tuple[np.ndarray, float]:
    """meshoptimizer simplify to the reduce target, never past ``max_error`` (meshoptimizer's
    target error: relative to the mesh's extent, an estimate), without losing small pieces.
    ``locked`` (N,) bool: vertices that must stay.

    An edge-collapse simplifier working on the whole mesh can collapse a small closed piece
    (a bone chip, a calcification) to nothing or to a sliver: its own quadric error stays
    tiny, yet the piece is gone and the measured deviation jumps to its distance from the
    rest of the surface (70 mm on CThead). So tiny pieces are kept whole, small pieces are
    simplified one by one to the same reduce rate, and only large pieces share one target.
    """
    faces = np.ascontiguousarray(mesh.faces)
    face_root = _roots(faces, mesh.n_vertices)[faces[:, 0]]
    size = np.bincount(face_root, minlength=mesh.n_vertices)[face_root]
    whole = size < _SMALL_PIECE_TRIANGLES / (1.0 - reduce)
    small = ~whole & (size < _OWN_TARGET_TRIANGLES)
    large = size >= _OWN_TARGET_TRIANGLES
    kept, error = [faces[whole]], 0.0
    lock = np.zeros(mesh.n_vertices, np.uint8) if locked is None else locked.astype(np.uint8)
    if small.any():
        kept.append(
            _each_piece(faces[small], face_root[small], mesh.vertices, reduce, max_error, lock)
        )
    if large.any():
        # the large pieces make up what the kept and small pieces left of the target
        budget = (1.0 - reduce) * len(faces) - sum(len(k) for k in kept)
        share = min(1.0, max(budget, 1.0) / int(large.sum()))
        faces_large, error = _quadric_all(faces[large], mesh.vertices, 1.0 - share, max_error, lock)
        kept.append(faces_large)
    return np.concatenate(kept), error


def _each_piece(
    faces: np.ndarray,
    face_root: np.ndarray,
    vertices: np.ndarray,
    reduce: float,
    max_error: float,
    lock: np.ndarray,
) -> np.ndarray:
    """Simplify each connected piece of ``faces`` on its own to the reduce rate."""
    order = np.argsort(face_root, kind="stable")
    starts = np.flatnonzero(np.diff(face_root[order])) + 1
    positions = np.ascontiguousarray(vertices, dtype=np.float32)
    pieces = []
    for piece in np.split(faces[order].astype(np.uint32), starts):
        target = int(round(3 * len(piece) * (1.0 - reduce)))
        # SPARSE: a piece touches few vertices; cost follows the piece, not the buffer
        out, _ = _simplify(
            piece.ravel(), positions, target, max_error, meshoptimizer.SIMPLIFY_SPARSE, lock
        )
        pieces.append(out.reshape(-1, 3).astype(np.int32))
    return np.concatenate(pieces)


def _quadric_all(
    faces: np.ndarray, vertices: np.ndarray, reduce: float, max_error: float, lock: np.ndarray
) -> tuple[np.ndarray, float]:
    """meshoptimizer simplify of ``faces`` (F, 3) to the reduce target.

    Large meshes go in two phases: slabs simplified on all cores with their cut borders
    locked, each to twice its final share, then the merged mesh in one call. The first
    phase does most of the collapses (the cheap ones), so the serial second phase runs on a
    fifth of the triangles. Measured on CThead (817 k triangles to 10 %, 2 cores): 0.24 s
    against 0.50 s for one call, with less CPU time in all (meshoptimizer's cost grows faster
    than the triangle count); the mean deviation the same (0.063 mm), the maximum 2.7 mm
    where one call loses a bone chip (70 mm). Sixteen slabs, two at a time, also keep
    meshoptimizer's working memory to a fraction.
    """
    if faces.dtype == np.int32 and faces.flags.c_contiguous:
        faces = faces.view(np.uint32)  # indices are >= 0: the same bits, no copy
    faces = np.ascontiguousarray(faces, dtype=np.uint32)
    positions = np.ascontiguousarray(vertices, dtype=np.float32)
    target = int(round(3 * len(faces) * (1.0 - reduce)))
    first_keep = _FIRST_PHASE_FACTOR * (1.0 - reduce)
    if len(faces) < _PARALLEL_MIN_TRIANGLES or first_keep > _FIRST_PHASE_MAX_KEEP:
        kept, error = _simplify(faces.ravel(), positions, target, max_error, 0, lock)
        return kept.reshape(-1, 3).astype(np.int32), error
    # SPARSE: each slab touches a sixteenth of the vertex buffer; LOCK_BORDER: its cut edges
    # must stay as they are so that the slabs still meet
    options = meshoptimizer.SIMPLIFY_LOCK_BORDER | meshoptimizer.SIMPLIFY_SPARSE
    with ThreadPoolExecutor(min(os.cpu_count() or 1, _SLABS)) as pool:
        phase = list(
            pool.map(
                lambda idx: _simplify(
                    idx, positions, int(len(idx) * first_keep), max_error, options, lock
                ),
                _slabs(faces, positions, _SLABS),
            )
        )
    merged = np.concatenate([kept for kept, _ in phase])
    kept, error = _simplify(
        merged, positions, target, max_error, meshoptimizer.SIMPLIFY_SPARSE, lock
    )
    # the two phases' errors add up at most
    return kept.reshape(-1, 3).astype(np.int32), error + max(err for _, err in phase)
