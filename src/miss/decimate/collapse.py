"""Half-edge collapse within a proven bound, cheapest first by quadric error: the numba
kernels live in :mod:`miss.decimate._collapse`; this is how :func:`miss.decimate.decimate`
calls them.

A large mesh runs each stage in slabs first, as schroeder's passes do
(:func:`miss.decimate._fan.domains`): the slabs' vertices share no neighbour, so their
collapses run side by side on up to as many threads as there are cores, each slab to its
share of the target, each with a heap of its own; then the whole mesh, serially, with
what the slabs left (the guard between them, vertices whose fans changed).
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from miss.types import Mesh

#: The stages of a run, as fractions of its bound: the cheapest collapses spend half the
#: budget everywhere before any spends all of it (on CThead bone at 0.002, with every
#: neighbour weighed: 115 808 triangles against 121 334 in one stage, for a third more
#: time; 113 426 in three, for two thirds more).
STAGES: tuple[float, ...] = (0.5, 1.0)
# A run takes one slab per this many triangles, a power of two up to _MAX_SLABS (as
# schroeder's); set by the mesh, not the machine, so that the output is the same anywhere.
_SLAB_FACES = 65_536
_MAX_SLABS = 4


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
    from miss.decimate._fan import vertex_faces  # numba: compiled on first use

    pts = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    work = np.array(mesh.faces, dtype=np.int32, order="C")  # a copy: edited in place
    locked = np.zeros(len(pts), np.bool_) if locked is None else locked.astype(np.bool_)
    target = math.floor(len(work) * (1.0 - reduce) + 1e-9)
    # distances within round-off of zero count as zero (as schroeder's)
    slack = 1e-12 * mesh.diagonal()
    vf, vdeg = vertex_faces(work, len(pts), _VALENCE_CAP)
    run = _Run(pts, work, vf, vdeg, locked)
    bound = 0.0
    for share in stages:
        bound = share * bound_mm + slack
        if run.stage(bound, target) <= target:
            break
    return work[run.alive], bound


# Largest number of triangles a vertex may carry (as schroeder's: vtkDecimate's Degree was 25).
_VALENCE_CAP = 32


class _Run:
    """One run's state: the mesh being collapsed (faces, alive, adjacency, quadrics, each
    triangle's error, each vertex's need and heap position)."""

    def __init__(
        self, pts: np.ndarray, faces: np.ndarray, vf: np.ndarray, vdeg: np.ndarray, locked
    ) -> None:
        from miss.decimate._collapse import plane_quadrics

        self.pts, self.faces, self.vf, self.vdeg, self.locked = pts, faces, vf, vdeg, locked
        self.q = plane_quadrics(pts, faces)
        self.alive = np.ones(len(faces), np.bool_)
        self.terr = np.zeros(len(faces))
        self.need = np.zeros(len(pts))
        self.pos = np.full(len(pts), -1, np.int32)
        self.n_alive = len(faces)
        self.count = _slab_count(len(faces))

    def _one(self, bound: float, n_alive: int, stop: int, visit, owner, me: int) -> int:
        from miss.decimate._collapse import collapse_stage, scratch

        heap = (np.zeros(len(visit)), np.zeros(len(visit), np.int32), self.pos)
        return collapse_stage(
            self.pts, self.faces, self.alive, self.vf, self.vdeg, self.q, self.terr,
            self.locked, bound, n_alive, stop, visit, owner, me, heap, self.need,
            scratch(self.vf.shape[1]),
        )  # fmt: skip

    def stage(self, bound: float, target: int) -> int:
        """One stage at ``bound`` (mm): the slabs side by side, then the whole mesh.
        Returns the live triangles."""
        if self.count > 1:
            self._slabs(bound, target)
        everything = np.arange(len(self.pts), dtype=np.int32)
        owner = np.zeros(len(self.pts), np.int32)
        self.n_alive = self._one(bound, self.n_alive, target, everything, owner, 0)
        return self.n_alive

    def _slabs(self, bound: float, target: int) -> None:
        from miss.decimate._fan import domains, slabs

        if not hasattr(self, "slab"):
            self.slab = slabs(self.pts, self.faces, self.count)
        order, starts = domains(self.faces, self.alive, self.vdeg, self.slab, self.count)
        owner = np.full(len(self.pts), -1, np.int32)  # the guard's: no slab's
        visits = [order[starts[d] : starts[d + 1]] for d in range(self.count)]
        for d, visit in enumerate(visits):
            owner[visit] = d
        # each slab stops at its share (by vertices) of the triangles to remove
        share = (self.n_alive - target) / max(sum(len(v) for v in visits), 1)
        n = self.n_alive
        with ThreadPoolExecutor(min(self.count, os.cpu_count() or 1)) as pool:
            runs = [
                pool.submit(self._one, bound, n, n - math.floor(share * len(v)), v, owner, d)
                for d, v in enumerate(visits)
            ]
            self.n_alive -= sum(n - r.result() for r in runs)


def _slab_count(n_faces: int) -> int:
    """Slabs for a run: one per ``_SLAB_FACES`` triangles, a power of two up to
    ``_MAX_SLABS``."""
    count = 1
    while count < _MAX_SLABS and n_faces >= 2 * count * _SLAB_FACES:
        count *= 2
    return count


def warm_up() -> None:
    """Compile (or load from numba's cache) collapse's kernels now, on a small sphere."""
    from miss.decimate._fan import warm_sphere

    pts, faces = warm_sphere()
    collapse(Mesh(pts.astype(np.float32), faces), 0.5, 0.01)
