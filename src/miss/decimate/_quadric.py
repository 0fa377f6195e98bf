"""Compiled (numba) versions of the quadric's two hot loops, and when to use them (the
surface's seam loop, of the same kind, is :mod:`miss.surface._seams`).

A process pays numba's start once (its import and the first kernel's load: 0.6-0.9 s on
the 2-core test machine); after that each of these runs in a few milliseconds, several
times faster than its whole-array numpy version. A process that has numba loaded anyway
(a server's worker, which measures every model's deviation with it; a benchmark) uses
them; one that has not (``miss convert``, ``miss.decimate(measure=False)``) takes the
numpy versions beside their callers, which give the same results bit for bit
(tests/test_jit.py), rather than pay the start for milliseconds of work. Callers check
``"numba" in sys.modules`` and import this module only when it holds.
"""

from __future__ import annotations

import numpy as np

from miss._numba import njit


@njit(cache=True)
def partition(
    faces: np.ndarray, coord: np.ndarray, cuts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Faces (F, 3) bucketed by the slab (between ``cuts``) of their centroid's ``coord``:
    flat uint32 indices slab after slab, and the slabs' first faces (len(cuts) + 2)."""
    n = faces.shape[0]
    slab = np.empty(n, dtype=np.int64)
    starts = np.zeros(len(cuts) + 2, dtype=np.int64)
    for f in range(n):
        c = coord[faces[f, 0]] + coord[faces[f, 1]] + coord[faces[f, 2]]
        s = np.searchsorted(cuts, c, side="right")
        slab[f] = s
        starts[s + 1] += 1
    starts = np.cumsum(starts)
    at = starts[:-1].copy()
    out = np.empty(3 * n, dtype=np.uint32)
    for f in range(n):
        p = 3 * at[slab[f]]
        at[slab[f]] += 1
        out[p], out[p + 1], out[p + 2] = faces[f, 0], faces[f, 1], faces[f, 2]
    return out, starts


@njit(cache=True)
def roots(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(N,) connected-component root of every vertex: its piece's smallest vertex index.

    Union-find over the faces' edges, always linking the larger root under the smaller,
    so that one final pass in index order resolves every vertex in O(1).
    """
    parent = np.arange(n_vertices)
    for f in range(faces.shape[0]):
        for k in range(1, 3):
            a, b = faces[f, 0], faces[f, k]
            while parent[a] != a:
                parent[a] = parent[parent[a]]
                a = parent[a]
            while parent[b] != b:
                parent[b] = parent[parent[b]]
                b = parent[b]
            if a < b:
                parent[b] = a
            elif b < a:
                parent[a] = b
    for v in range(n_vertices):
        parent[v] = parent[parent[v]]  # parent[v] <= v is already resolved
    return parent
