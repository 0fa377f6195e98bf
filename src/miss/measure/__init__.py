"""The distance between two surfaces, in millimetres, and a decimation's bound check.

:func:`deviation` and :func:`side_of` measure with the native kernels
(:mod:`miss.measure._native`, ``_nearest.cpp``) or numba's (:mod:`miss.measure._jit`),
the same figures to the bit: numba's where numba is loaded already or the extension was
not built. The decimation's check (:func:`miss.measure._jit.bound_check`), the child
process that measures for a fresh command (:mod:`miss.measure.measurer`) and the
segment and triangle distances Schroeder's kernels share (:mod:`miss.measure.distance`)
are inside too."""

from __future__ import annotations

import sys

from miss.measure._core import Deviation, Side
from miss.measure._native import native, native_deviation, native_side_of
from miss.types import Mesh

__all__ = ["Deviation", "Side", "deviation", "native", "side_of"]


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
