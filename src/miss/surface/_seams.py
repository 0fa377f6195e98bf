"""numba's loop for the seams of a slab-by-slab surface (:func:`miss.surface._keep_and_number`
has the numpy version, the same faces bit for bit: tests/test_jit.py); used where numba is
loaded already (see :mod:`miss.decimate._quadric`)."""

from __future__ import annotations

import numpy as np

from miss._numba import njit


@njit(cache=True)
def keep_and_number(faces, beyond, ids, start):
    """Faces without a vertex ``beyond``, renumbered: vertices with an id (from the seam
    below) keep it, the others get start, start + 1, ... in first-use order. Returns the
    faces (int32) and the local indices of the newly numbered vertices; fills ``ids``."""
    out = np.empty(faces.shape, dtype=np.int32)
    order = np.empty(len(ids), dtype=np.int64)
    n_faces, n_new = 0, 0
    for f in range(len(faces)):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        if beyond[a] or beyond[b] or beyond[c]:
            continue
        for k in range(3):
            v = faces[f, k]
            if ids[v] < 0:
                ids[v] = start + n_new
                order[n_new] = v
                n_new += 1
            out[n_faces, k] = ids[v]
        n_faces += 1
    return out[:n_faces], order[:n_new]
