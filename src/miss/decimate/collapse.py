"""Half-edge collapse within a proven bound, cheapest first by quadric error: the numba
kernels live in :mod:`miss.decimate._collapse`; this is how :func:`miss.decimate.decimate`
calls them."""

from __future__ import annotations

import math

import numpy as np

from miss.types import Mesh

#: The stages of a run, as fractions of its bound: the cheapest collapses spend the
#: budget first everywhere before any spends all of it (as schroeder's rising bound).
STAGES: tuple[float, ...] = (0.5, 1.0)


def collapse(
    mesh: Mesh,
    reduce: float,
    bound_mm: float,
    locked: np.ndarray | None = None,
    stages: tuple[float, ...] = STAGES,
) -> tuple[np.ndarray, float]:
    """Face indices kept, and the bound of the last stage run (mm).

    Parameters
    ----------
    mesh : Mesh
        The input; its vertices are never moved, and the faces returned index them.
    reduce : float
        Target fraction of triangles to remove, in [0, 1).
    bound_mm : float
        The most the output may deviate from the input, two-sided, everywhere (mm): each
        triangle carries the error spent on it, and a collapse goes only if that stays
        within the bound.
    locked : (N,) bool array, optional
        Vertices that stay (they may still take in a neighbour's triangles).
    stages : tuple of float
        Fractions of ``bound_mm``, rising, each run until no collapse is left within it.
    """
    from miss.decimate._collapse import _VALENCE_CAP, collapse_run  # numba: compiled on first use

    pts = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    work = np.array(mesh.faces, dtype=np.int32, order="C")  # a copy: edited in place
    if locked is None:
        locked = np.zeros(len(pts), dtype=np.bool_)
    target = math.floor(len(work) * (1.0 - reduce) + 1e-9)
    # distances within round-off of zero count as zero (as schroeder's)
    slack = 1e-12 * mesh.diagonal()
    bounds = np.asarray([s * bound_mm + slack for s in stages], dtype=np.float64)
    alive, _, last = collapse_run(
        pts, work, np.ascontiguousarray(locked, dtype=np.bool_), bounds, target, _VALENCE_CAP
    )
    return work[alive], float(last)
