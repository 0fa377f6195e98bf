"""numba, started without the one part of its start that MISS never uses.

numba's first kernel (compiled, or loaded from its cache) imports ``numba.np.arraymath``,
which checks for a BLAS by importing ``scipy.linalg`` whole: 0.14-0.46 s on the 2-core
test machine (scipy's array-API layer, ``numpy.f2py``), a third of numba's start in a fresh
process and the only reason a job that measures imports scipy at all. The answer only
chooses how jitted ``np.correlate`` and ``np.convolve`` multiply; MISS's kernels use
neither, nor any BLAS. So that module is imported here with the check answered "no BLAS".
Jitted ``np.dot`` and ``np.linalg``, were a kernel to use them, still import the BLAS
themselves when they are compiled (numba's own ``ensure_blas``, left as it was).

MISS's modules take numba's names from here, so that this runs before their first kernel.
"""

from __future__ import annotations

from numba import njit, prange


def _without_blas_check() -> None:
    """Import ``numba.np.arraymath`` with its module-level BLAS check answered "none"
    (nothing happens where numba has loaded it already, or is laid out otherwise)."""
    import sys

    if "numba.np.arraymath" in sys.modules:
        return
    try:
        from numba.np import linalg
    except ImportError:
        return
    real = getattr(linalg, "ensure_blas", None)
    if real is None:
        return

    def unchecked() -> None:
        raise ImportError("BLAS not looked for: MISS's kernels use none")

    linalg.ensure_blas = unchecked
    try:
        import numba.np.arraymath  # noqa: F401
    finally:
        linalg.ensure_blas = real


_without_blas_check()

__all__ = ["njit", "prange"]
