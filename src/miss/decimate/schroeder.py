"""The paper's vertex decimation (Schroeder, Zarge & Lorensen 1992): the numba kernels
live in :mod:`miss.decimate._schroeder`; this is how :func:`miss.decimate.decimate` calls them."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from miss.types import Mesh


def schroeder(
    mesh: Mesh,
    reduce: float,
    bound_mm: float,
    max_mm: float,
    paper_passes: int = 0,
    locked: np.ndarray | None = None,
    done: Callable[[float], None] | None = None,
) -> tuple[np.ndarray, float]:
    """Face indices kept, and the last bound used (mm). Triangles carry the error spent
    on them (accumulated error); ``locked`` (N,) bool: vertices that stay; ``done(fraction)``
    hears after each pass how much of the removal is done (0..1)."""
    from miss.decimate._schroeder import schroeder_decimate  # numba: compiled on first use

    faces, info = schroeder_decimate(
        mesh.vertices.astype(np.float64),
        mesh.faces,
        reduce=reduce,
        error_bound=bound_mm,
        max_error=max_mm,
        paper_passes=paper_passes,
        accumulate=True,
        locked=locked,
        done=done,
    )
    return faces, float(info["final_bound_mm"])


def warm_up() -> None:
    """Compile (or load from numba's cache) schroeder's kernels now, on a small sphere: for
    a process that runs jobs later (a server's spare worker)."""
    from miss.decimate._schroeder import warm_up as warm

    warm()
