"""Kernels on a vertex's fan shared by the bounded simplifiers: vertex removal
(:mod:`miss.decimate._schroeder`) and half-edge collapse (:mod:`miss.decimate._collapse`).

A fan is a vertex's triangles chained round it (:func:`order_fan`); both methods replace a
fan by triangles over its loop (:func:`commit`) and bound the distance between the two
(:func:`overlay_gap`), which each new triangle then carries as its accumulated error.
The face array is edited in place; vertex -> face adjacency is a fixed-capacity table
(:func:`vertex_faces`).
"""

from __future__ import annotations

import math

import numpy as np

from miss._numba import njit
from miss.measure.distance import NO_REFCOUNT, segment_sq
from miss.types import column_bounds


@njit(cache=True, inline="always")
def cross(ax, ay, az, bx, by, bz):
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


@njit(cache=True, inline="always")
def cross2(ax, ay, bx, by):
    return ax * by - ay * bx


@njit(cache=True, inline="always")
def frame(nx, ny, nz):
    """Unit vectors e, f with (e, f, n) right-handed, for the unit normal n: e built from the
    axis n is least aligned with."""
    if abs(nx) <= abs(ny) and abs(nx) <= abs(nz):
        ex, ey, ez = 0.0, nz, -ny
    elif abs(ny) <= abs(nz):
        ex, ey, ez = -nz, 0.0, nx
    else:
        ex, ey, ez = ny, -nx, 0.0
    el = math.sqrt(ex * ex + ey * ey + ez * ez)
    ex, ey, ez = ex / el, ey / el, ez / el
    fx, fy, fz = cross(nx, ny, nz, ex, ey, ez)
    return ex, ey, ez, fx, fy, fz


@njit(cache=True, **NO_REFCOUNT)
def edge_exists(faces, vf, vdeg, a, b):
    """True when some live triangle holds both vertices a and b."""
    for k in range(vdeg[a]):
        f = vf[a, k]
        if faces[f, 0] == b or faces[f, 1] == b or faces[f, 2] == b:
            return True
    return False


@njit(cache=True, **NO_REFCOUNT)
def face_exists(faces, vf, vdeg, a, b, c):
    """True when a live triangle has the corners a, b and c."""
    for k in range(vdeg[a]):
        f = vf[a, k]
        hits = 0
        for m in range(3):
            if faces[f, m] == b or faces[f, m] == c:
                hits += 1
        if hits == 2:
            return True
    return False


@njit(cache=True, inline="always")
def chain_fan(v, vf, n, start, fan, loop, a_s, b_s):
    """Chain v's n triangles from triangle `start`, each followed by the first whose leading
    vertex is its trailing one. Returns (n_loop, closed), n_loop = -1 if the chain breaks."""
    k = start
    for step in range(n):
        fan[step] = vf[v, k]
        loop[step] = a_s[k]
        if step == n - 1:
            break
        nxt = -1
        for m in range(n):
            if a_s[m] == b_s[k]:
                nxt = m
                break
        if nxt == -1:
            return -1, False
        k = nxt
    if b_s[k] == loop[0]:
        return n, True
    loop[n] = b_s[k]
    return n + 1, False


@njit(cache=True, inline="always")
def order_fan(v, faces, vf, vdeg, fan, loop, a_s, b_s):
    """Order v's triangles into a chain (v, loop[k], loop[k+1]).

    Returns (n_loop, closed). A closed fan of n triangles gives n loop vertices, an open
    (boundary) fan n + 1; n_loop = -1 means the neighbourhood is not a manifold disc or
    half-disc (complex vertex).
    """
    n = vdeg[v]
    for k in range(n):
        f = vf[v, k]
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        if i0 == v:
            a_s[k], b_s[k] = i1, i2
        elif i1 == v:
            a_s[k], b_s[k] = i2, i0
        else:
            a_s[k], b_s[k] = i0, i1
    # Follow the chain from the first triangle; if it breaks, the fan is open and is followed
    # again from its one triangle whose leading vertex trails no other.
    n_loop, closed = chain_fan(v, vf, n, 0, fan, loop, a_s, b_s)
    if n_loop < 0:
        start = -1
        for k in range(n):
            trails = False
            for m in range(n):
                if b_s[m] == a_s[k]:
                    trails = True
                    break
            if not trails:
                if start != -1:
                    return -1, False
                start = k
        if start == -1:
            return -1, False
        n_loop, closed = chain_fan(v, vf, n, start, fan, loop, a_s, b_s)
        if n_loop < 0 or closed:
            return -1, False
    # Distinct loop vertices mean one single cycle through all triangles.
    for i in range(n_loop):
        for j in range(i + 1, n_loop):
            if loop[i] == loop[j]:
                return -1, False
    return n_loop, closed


@njit(cache=True, inline="always")
def fan_normals(pts, faces, fan, n, fn):
    """Unnormalised normals (length = 2 x area, mm^2) of the n fan triangles into fn (n, 3)."""
    for k in range(n):
        f = fan[k]
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        fn[k, 0], fn[k, 1], fn[k, 2] = cross(
            pts[b, 0] - pts[a, 0],
            pts[b, 1] - pts[a, 1],
            pts[b, 2] - pts[a, 2],
            pts[c, 0] - pts[a, 0],
            pts[c, 1] - pts[a, 1],
            pts[c, 2] - pts[a, 2],
        )


@njit(cache=True, **NO_REFCOUNT)
def unit_normal_sum(fn, first, last, n, out):
    """Unit sum of fan normals first .. last-1 (indices taken modulo n) into out; False if zero."""
    out[0] = out[1] = out[2] = 0.0
    for k in range(first, last):
        kk = k % n
        out[0] += fn[kk, 0]
        out[1] += fn[kk, 1]
        out[2] += fn[kk, 2]
    length = math.sqrt(out[0] ** 2 + out[1] ** 2 + out[2] ** 2)
    if length == 0.0:
        return False
    out[0] /= length
    out[1] /= length
    out[2] /= length
    return True


@njit(cache=True, **NO_REFCOUNT)
def overlay_gap(pts, v, fn, n, loop, n_loop, tris, ntri, nrm, xyh, limit):
    """A bound (mm) on the two-sided distance between v's fan and the ntri triangles that
    fill its hole (loop positions in tris), or inf where this bound does not apply (the
    deletion is then refused).

    Both surfaces are seen along the fan's mean normal N. Where every fan triangle and every
    new triangle faces along N, and each covers the loop's outline once, both are graphs
    of a height over that outline: a point of one lies straight above (or below) a point of
    the other, so their distance, either way, is at most the difference of the two heights
    there (nrm, xyh: scratch for N and the loop's coordinates). That difference is
    linear where a fan triangle and a new triangle overlap, so it is largest at a corner of
    such an overlap: v itself, or where a spoke (v to a loop vertex) crosses a new chord;
    the loop vertices and edges lie on both (0). An open fan
    (a boundary vertex) reaches past the chord that closes its loop: there the fan's
    distance to that chord, largest at v or where a spoke crosses it, bounds it.

    A bound, not a sample: with the error each triangle already carries (see miss.decimate._schroeder._try_delete)
    the whole surface stays within it however deletions chain, where a share measured at
    points (v, midpoints, centroids) misses where the surfaces part between them
    (benchmarks/bounds.py's "dense max"). Returns as soon as it passes limit.
    """
    if not unit_normal_sum(fn, 0, n, n, nrm):
        return np.inf
    nx, ny, nz = nrm[0], nrm[1], nrm[2]
    for k in range(n):
        if fn[k, 0] * nx + fn[k, 1] * ny + fn[k, 2] * nz <= 0.0:
            return np.inf  # a fan triangle folded back: no height over the outline
    ex, ey, ez, fx, fy, fz = frame(nx, ny, nz)
    # v relative: coordinates stay small, so the areas below keep their digits
    ox, oy, oz = pts[v, 0], pts[v, 1], pts[v, 2]
    closed = n_loop == n
    # loop vertices' (x, y, h); v is (0, 0, 0)
    xs, ys, hs = xyh[:, 0], xyh[:, 1], xyh[:, 2]
    for k in range(n_loop):
        u = loop[k]
        dx, dy, dz = pts[u, 0] - ox, pts[u, 1] - oy, pts[u, 2] - oz
        xs[k] = ex * dx + ey * dy + ez * dz
        ys[k] = fx * dx + fy * dy + fz * dz
        hs[k] = nx * dx + ny * dy + nz * dz
    outline = 0.0  # twice the loop polygon's area (closed by the chord from its last to first)
    scale = 0.0
    for k in range(n_loop):
        j = (k + 1) % n_loop
        outline += cross2(xs[k], ys[k], xs[j], ys[j])
        scale += xs[k] * xs[k] + ys[k] * ys[k]
    fan = 0.0
    for k in range(n if closed else n_loop - 1):
        j = (k + 1) % n_loop
        fan += cross2(xs[k], ys[k], xs[j], ys[j])
    patch = 0.0
    for t in range(ntri):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        area = cross2(xs[b] - xs[a], ys[b] - ys[a], xs[c] - xs[a], ys[c] - ys[a])
        if area <= 0.0:
            return np.inf  # a new triangle folded back
        patch += area
    tol = 1e-9 * scale
    if abs(patch - outline) > tol:
        return np.inf
    gap = 0.0
    if closed:
        if abs(fan - outline) > tol:
            return np.inf  # the fan winds round v more than once
        # v's height over the new triangle beneath it (the one it lies in most)
        best, height = -np.inf, 0.0
        for t in range(ntri):
            a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
            area = cross2(xs[b] - xs[a], ys[b] - ys[a], xs[c] - xs[a], ys[c] - ys[a])
            la = cross2(xs[b], ys[b], xs[c], ys[c]) / area
            lb = cross2(xs[c], ys[c], xs[a], ys[a]) / area
            lc = 1.0 - la - lb
            inside = min(la, lb, lc)
            if inside > best:
                best, height = inside, la * hs[a] + lb * hs[b] + lc * hs[c]
        gap = abs(height)
    else:
        # past the closing chord: v, beyond it or on it (a straight border; else the
        # outlines differ), to that chord
        a, b = n_loop - 1, 0
        beyond = cross2(xs[b] - xs[a], ys[b] - ys[a], -xs[a], -ys[a])
        if beyond < -tol or abs(fan - outline - beyond) > tol:
            return np.inf
        ax, ay, az = pts[loop[a], 0] - ox, pts[loop[a], 1] - oy, pts[loop[a], 2] - oz
        bx, by, bz = pts[loop[b], 0] - ox, pts[loop[b], 1] - oy, pts[loop[b], 2] - oz
        gap = math.sqrt(segment_sq(0.0, 0.0, 0.0, ax, ay, az, bx, by, bz))
    if gap > limit:
        return gap
    for i in range(n_loop):
        for t in range(ntri):
            for e in range(3):
                a, b = tris[t, e], tris[t, (e + 1) % 3]
                if a == i or b == i:
                    continue
                lo, hi = min(a, b), max(a, b)
                if hi - lo == 1 or (closed and lo == 0 and hi == n_loop - 1):
                    continue  # a loop edge: on the fan too
                # spoke 0 -> i against chord a -> b, in the plane
                sx, sy = xs[b] - xs[a], ys[b] - ys[a]
                d = cross2(xs[i], ys[i], sx, sy)
                if d == 0.0:
                    # parallel: no crossing, or (the chord through v) an overlap whose ends,
                    # v and loop vertices, are measured already
                    continue
                s = cross2(xs[a], ys[a], sx, sy) / d  # along the spoke
                r = cross2(xs[a], ys[a], xs[i], ys[i]) / d  # along the chord
                if 0.0 <= s <= 1.0 and 0.0 <= r <= 1.0:
                    gap = max(gap, abs(s * hs[i] - (hs[a] + r * (hs[b] - hs[a]))))
                    if gap > limit:
                        return gap
    return gap


@njit(cache=True, inline="always")
def commit(v, faces, alive, vf, vdeg, fan, n, loop, n_loop, tris, ntri, count):
    """Replace v's fan by the new triangles (tris: loop positions), reusing the fan's face slots.

    count is a scratch array of at least n_loop ints. Returns False, with nothing changed,
    when a loop vertex would carry more triangles than its row holds.
    """
    cap = vf.shape[1]
    closed = n_loop == n
    count[:n_loop] = 0
    for t in range(ntri):
        for c in range(3):
            count[tris[t, c]] += 1
    for t in range(n_loop):
        in_fan = 2 if closed or 0 < t < n_loop - 1 else 1
        if vdeg[loop[t]] - in_fan + count[t] > cap:
            return False
    for t in range(n_loop):
        u = loop[t]
        # Loop vertex t sat in fan triangles t - 1 and t (one of them at the ends of an open fan).
        f_prev = fan[t - 1] if t > 0 else (fan[n - 1] if closed else -1)
        f_next = fan[t] if t < n else -1
        w = 0
        for k in range(vdeg[u]):
            f = vf[u, k]
            if f != f_prev and f != f_next:
                vf[u, w] = f
                w += 1
        vdeg[u] = w
    for t in range(ntri):
        f = fan[t]
        for c in range(3):
            u = loop[tris[t, c]]
            faces[f, c] = u
            vf[u, vdeg[u]] = f
            vdeg[u] += 1
    for t in range(ntri, n):
        alive[fan[t]] = False
    vdeg[v] = 0
    return True


@njit(cache=True)
def vertex_faces(faces, n_vertices, min_cap):
    """Vertex -> face table: (N, cap) int32 rows of face ids and (N,) int32 row lengths."""
    vdeg = np.zeros(n_vertices, np.int32)
    for f in range(faces.shape[0]):
        for c in range(3):
            vdeg[faces[f, c]] += 1
    cap = max(min_cap, vdeg.max() if n_vertices > 0 else 0)
    vf = np.full((n_vertices, cap), -1, np.int32)
    vdeg[:] = 0
    for f in range(faces.shape[0]):
        for c in range(3):
            u = faces[f, c]
            vf[u, vdeg[u]] = f
            vdeg[u] += 1
    return vf, vdeg


def slabs(pts: np.ndarray, faces: np.ndarray, count: int) -> np.ndarray:
    """(N,) int32: the slab of each vertex, ``count`` slabs across the mesh's longest axis
    cut at quantiles of its vertices (see domains)."""
    used = np.zeros(len(pts), dtype=bool)
    used[faces.ravel()] = True
    lo, hi = column_bounds(pts[used])  # np.ptp(axis=0) walks (N, 3) with a stride: 20x slower
    axis = int(np.argmax(hi - lo))
    cuts = np.quantile(pts[used, axis], np.arange(1, count) / count)
    return np.searchsorted(cuts, pts[:, axis], side="right").astype(np.int32)


@njit(cache=True, nogil=True)
def domains(faces, alive, vdeg, slab, count):
    """The vertices a pass may decimate side by side, slab by slab, and the rest (the guard:
    the corners of every live triangle that spans two slabs), each in index order. Returns
    (order, starts): slab d's vertices are order[starts[d]:starts[d + 1]], the guard's
    order[starts[count]:].

    A slab's vertices then have neighbours in their own slab only, and no two slabs share a
    neighbour. Deleting a vertex joins its neighbours, so that stays true while the guard
    stays (a slab's deletions join vertices of that slab): each slab's deletions read and
    write only its own vertices' rows and the triangles that touch them, whatever the other
    slabs do, and the result is the same however the slabs are run.
    """
    guard = np.zeros(len(slab), dtype=np.bool_)
    for f in range(len(faces)):
        if alive[f]:
            a, b, c = slab[faces[f, 0]], slab[faces[f, 1]], slab[faces[f, 2]]
            if a != b or b != c:
                guard[faces[f, 0]] = guard[faces[f, 1]] = guard[faces[f, 2]] = True
    starts = np.zeros(count + 2, dtype=np.int64)
    for v in range(len(slab)):
        if vdeg[v] > 0:
            starts[(count if guard[v] else slab[v]) + 1] += 1
    for d in range(1, count + 2):
        starts[d] += starts[d - 1]
    order = np.empty(starts[count + 1], dtype=np.int32)
    fill = starts[:-1].copy()
    for v in range(len(slab)):
        if vdeg[v] > 0:
            d = count if guard[v] else slab[v]
            order[fill[d]] = v
            fill[d] += 1
    return order, starts


def warm_sphere() -> tuple[np.ndarray, np.ndarray]:
    """A small closed sphere, (points (N, 3) float64, faces (F, 3) int32): what each
    bounded method's ``warm_up`` decimates to compile (or load) its kernels."""
    import vtk
    from vtk.util import numpy_support

    source = vtk.vtkSphereSource()
    source.SetThetaResolution(24)
    source.SetPhiResolution(24)
    source.Update()
    poly = source.GetOutput()
    pts = numpy_support.vtk_to_numpy(poly.GetPoints().GetData()).astype(np.float64)
    faces = numpy_support.vtk_to_numpy(poly.GetPolys().GetConnectivityArray()).reshape(-1, 3)
    return pts, faces.astype(np.int32)
