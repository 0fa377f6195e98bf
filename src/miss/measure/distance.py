"""Squared distances from a point to a segment and to a triangle (numba, inlined where
they are called): the measurement's kernels (:mod:`miss.measure._jit`) and Schroeder's
(:mod:`miss.decimate._schroeder`) share them."""

from __future__ import annotations

from typing import Any

from numba.core.cpu import CPUTargetOptions

from miss._numba import njit


@njit(cache=True, inline="always")
def dot(ax, ay, az, bx, by, bz):
    """The dot product of vectors a and b, given by coordinates."""
    return ax * bx + ay * by + az * bz


@njit(cache=True, inline="always")
def segment_sq(px, py, pz, ax, ay, az, bx, by, bz):
    """Squared distance from point p to segment ab (a point when a == b)."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    length2 = dot(abx, aby, abz, abx, aby, abz)
    t = 0.0 if length2 == 0.0 else min(max(dot(abx, aby, abz, apx, apy, apz) / length2, 0.0), 1.0)
    qx, qy, qz = apx - t * abx, apy - t * aby, apz - t * abz
    return dot(qx, qy, qz, qx, qy, qz)


#: A triangle whose squared sine (|ab x ac|^2 / (|ab|^2 |ac|^2)) is below this is measured as
#: its three edges: the region tests' products cancel there. With 1e-24 here, a triangle
#: whose squared sine was 1.4e-24 (sides about 10 mm) gave 0.148 mm for a point on it (a
#: random case of tests/test_deviation.py); at 1e-20 its edges stand for it within 1e-10 of
#: its sides.
SLIVER = 1e-20


@njit(cache=True, inline="always")
def triangle_sq(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Squared distance from point p to triangle abc (Ericson, Real-Time Collision Detection
    5.1.5), on coordinates rather than arrays so that the search's loop keeps them in
    registers."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    nx, ny, nz = aby * acz - abz * acy, abz * acx - abx * acz, abx * acy - aby * acx
    scale = dot(abx, aby, abz, abx, aby, abz) * dot(acx, acy, acz, acx, acy, acz)
    if dot(nx, ny, nz, nx, ny, nz) <= SLIVER * scale or scale == 0.0:
        # a sliver or a point: the region tests below would divide by zero
        return min(
            segment_sq(px, py, pz, ax, ay, az, bx, by, bz),
            segment_sq(px, py, pz, bx, by, bz, cx, cy, cz),
            segment_sq(px, py, pz, cx, cy, cz, ax, ay, az),
        )
    apx, apy, apz = px - ax, py - ay, pz - az
    d1, d2 = dot(abx, aby, abz, apx, apy, apz), dot(acx, acy, acz, apx, apy, apz)
    if d1 <= 0.0 and d2 <= 0.0:
        return dot(apx, apy, apz, apx, apy, apz)
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3, d4 = dot(abx, aby, abz, bpx, bpy, bpz), dot(acx, acy, acz, bpx, bpy, bpz)
    if d3 >= 0.0 and d4 <= d3:
        return dot(bpx, bpy, bpz, bpx, bpy, bpz)
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5, d6 = dot(abx, aby, abz, cpx, cpy, cpz), dot(acx, acy, acz, cpx, cpy, cpz)
    if d6 >= 0.0 and d5 <= d6:
        return dot(cpx, cpy, cpz, cpx, cpy, cpz)
    vc, vb, va = d1 * d4 - d3 * d2, d5 * d2 - d1 * d6, d3 * d6 - d5 * d4
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        s, t = d1 / (d1 - d3), 0.0
    elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        s, t = 0.0, d2 / (d2 - d6)
    elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        s, t = 1.0 - w, w
    else:
        denom = va + vb + vc
        s, t = vb / denom, vc / denom
    qx, qy, qz = apx - s * abx - t * acx, apy - s * aby - t * acy, apz - s * abz - t * acz
    return dot(qx, qy, qz, qx, qy, qz)


#: njit options for kernels that allocate nothing: no reference counting of the arrays
#: they take and index (numba's own option; a numba without it counts them). Each
#: count is an atomic instruction on the array's shared header: in schroeder's pass loop
#: they were a fifth of the run (see :mod:`miss.decimate._schroeder`).
#: (``Any``: numba types each njit keyword apart, and the dict is spread into them.)
NO_REFCOUNT: dict[str, Any] = {"_nrt": False} if hasattr(CPUTargetOptions, "_nrt") else {}


@njit(cache=True, **NO_REFCOUNT)
def _pointtriangle_sq(p, a, b, c):
    """Squared distance from p to triangle abc, each a (3,) array."""
    return triangle_sq(p[0], p[1], p[2], a[0], a[1], a[2], b[0], b[1], b[2], c[0], c[1], c[2])
