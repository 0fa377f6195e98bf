"""The distance between two surfaces, in millimetres, and a decimation's bound check.

:func:`deviation` and :func:`side_of` measure with the native kernels
(:mod:`miss.measure._native`, ``_nearest.cpp``) or numba's (:mod:`miss.measure._jit`),
the same figures to the bit: numba's where numba is loaded already or the extension was
not built; :func:`surface_grid` picks its kernels the same way. The decimation's check
(:func:`bound_check` and what it is made of, numba's, loaded on first use), the child
process that measures for a fresh command (:mod:`miss.measure.measurer`) and the
segment and triangle distances Schroeder's kernels share (:mod:`miss.measure.distance`)
are inside too."""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING, Any

from miss.measure._core import Deviation, Side
from miss.measure._native import native, native_deviation, native_grid, native_side_of
from miss.types import Mesh

if TYPE_CHECKING:
    from miss.measure._jit import (
        BoundCheck,
        bound_check,
        distances_to,
        dropped_vertices,
        nearest_face,
        surface_adjacency,
    )

#: The decimation's check and its parts: numba's kernels, imported on first use (the
#: measurement above needs no numba where the native kernels are built).
_CHECK = (
    "BoundCheck",
    "bound_check",
    "distances_to",
    "dropped_vertices",
    "nearest_face",
    "surface_adjacency",
)

__all__ = [
    "BoundCheck",
    "Deviation",
    "Side",
    "bound_check",
    "deviation",
    "distances_to",
    "dropped_vertices",
    "native",
    "nearest_face",
    "side_of",
    "surface_adjacency",
    "surface_grid",
]


def __getattr__(name: str) -> Any:
    if name not in _CHECK:
        raise AttributeError(f"module 'miss.measure' has no attribute {name!r}")
    from miss.measure import _jit

    value = getattr(_jit, name)
    globals()[name] = value
    return value


def _jitted() -> bool:
    """Whether to measure with numba's kernels: where the native ones are not built, or
    where numba is loaded (see above). Either search takes either's grid."""
    return not native() or "numba" in sys.modules


def side_of(a: Mesh, samples: int = 100_000, seed: int = 0) -> Side:
    """``a``'s :class:`Side` of a :func:`deviation` with ``samples`` and ``seed``."""
    if _jitted():
        from miss.measure._jit import side_of as jitted

        return jitted(a, samples, seed)
    return native_side_of(a, samples, seed)


def deviation(
    a: Mesh, b: Mesh, samples: int = 100_000, seed: int = 0, side: Side | None = None
) -> Deviation:
    """Two-sided (symmetric Hausdorff-style) deviation between surfaces ``a`` and ``b``:
    ``samples`` points on each (its vertices, then area-weighted random points inside its
    triangles), each one's exact distance to the other surface; ``side``: ``a``'s half made
    already (:func:`side_of`, the same ``samples`` and ``seed``)."""
    if _jitted():
        from miss.measure._jit import deviation as jitted

        return jitted(a, b, samples, seed, side)
    return native_deviation(a, b, samples, seed, side)


def surface_grid(mesh: Mesh) -> tuple:
    """The cells of ``mesh``'s triangles (origin, cell size mm, counts, CSR offsets and
    items, each triangle's corners in a row) that a distance search takes; made once for
    several queries against one surface. Either kernels' cells, the same to the bit."""
    if _jitted():
        from miss.measure._jit import jit_grid

        return jit_grid(mesh)
    return native_grid(mesh)
