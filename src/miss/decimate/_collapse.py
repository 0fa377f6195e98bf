"""Half-edge collapse with a proven bound: the numba kernels of :mod:`miss.decimate.collapse`.

A half-edge collapse u -> v removes u and joins its triangles to v: u's fan is replaced
by the fan from v over u's loop (the two triangles on the edge u-v go). So it is a vertex
removal whose hole is filled by one particular triangulation, and the bound of vertex
removal holds for it unchanged (:func:`miss.decimate._fan.overlay_gap`: both fans as
heights over the old fan's mean plane, the difference largest at u or where a spoke of u
crosses a new edge from v). Every new triangle carries the error already spent on the
triangles it replaces plus that gap (accumulated error), and a collapse goes only if that
stays within the bound: the output is within the bound of the input everywhere.

What differs from vertex removal is the order and the choice: collapses go cheapest first
by Garland and Heckbert's quadric error (each vertex's plane quadric, summed into the
vertex that stays), from one heap, instead of index order at a rising bound; and a vertex
goes to the neighbour whose quadric cost is least among those whose collapse is valid.

A collapse is refused when it would change the topology (the link condition: a new edge
from v that already exists, or a vertex of valence 3 that tops a tetrahedron), turn a
triangle over or make one degenerate, leave a row of the vertex -> face table over its
capacity, or cost more than the bound. A boundary vertex goes only to a neighbour along
the boundary. Vertices never move and none are created: the output indexes the input's
vertex array.
"""

from __future__ import annotations

import heapq
import math

import numpy as np

from miss._numba import njit
from miss.decimate._fan import (
    commit,
    cross,
    edge_exists,
    face_exists,
    fan_normals,
    order_fan,
    overlay_gap,
    vertex_faces,
)

# Largest number of triangles a vertex may carry (as vertex removal's _VALENCE_CAP).
_VALENCE_CAP = 32
# New triangles with 2 x area below this fraction of the squared longest edge are degenerate.
_DEGENERATE = 1e-6


@njit(cache=True)
def plane_quadrics(pts, faces):
    """(N, 10) area-weighted plane quadrics of each vertex's triangles (Garland & Heckbert):
    the upper triangle of [n n^T, n d; n d, d^2], per triangle plane n . x + d = 0, times
    its area (mm^2), summed into its three corners."""
    q = np.zeros((len(pts), 10))
    for f in range(len(faces)):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        nx, ny, nz = cross(
            pts[b, 0] - pts[a, 0],
            pts[b, 1] - pts[a, 1],
            pts[b, 2] - pts[a, 2],
            pts[c, 0] - pts[a, 0],
            pts[c, 1] - pts[a, 1],
            pts[c, 2] - pts[a, 2],
        )
        length = math.sqrt(nx * nx + ny * ny + nz * nz)
        if length == 0.0:
            continue
        w = 0.5 * length
        nx, ny, nz = nx / length, ny / length, nz / length
        d = -(nx * pts[a, 0] + ny * pts[a, 1] + nz * pts[a, 2])
        row = (nx * nx, nx * ny, nx * nz, nx * d, ny * ny, ny * nz, ny * d, nz * nz, nz * d, d * d)
        for u in (a, b, c):
            for k in range(10):
                q[u, k] += w * row[k]
    return q


@njit(cache=True, inline="always")
def _quadric_at(q, u, x, y, z):
    """Vertex u's quadric error at (x, y, z), mm^4 (area times squared distance)."""
    return (
        q[u, 0] * x * x
        + 2.0 * q[u, 1] * x * y
        + 2.0 * q[u, 2] * x * z
        + 2.0 * q[u, 3] * x
        + q[u, 4] * y * y
        + 2.0 * q[u, 5] * y * z
        + 2.0 * q[u, 6] * y
        + q[u, 7] * z * z
        + 2.0 * q[u, 8] * z
        + q[u, 9]
    )


@njit(cache=True, inline="always")
def _collapse_cost(pts, q, u, v):
    """The quadric error of u and v together at v: the cost of collapsing u -> v."""
    x, y, z = pts[v, 0], pts[v, 1], pts[v, 2]
    return _quadric_at(q, u, x, y, z) + _quadric_at(q, v, x, y, z)


@njit(cache=True)
def _vertex_cost(pts, faces, vf, vdeg, q, u):
    """The least cost of collapsing u into one of its neighbours (inf: no neighbour)."""
    best = np.inf
    for k in range(vdeg[u]):
        f = vf[u, k]
        for c in range(3):
            w = faces[f, c]
            if w != u:
                best = min(best, _collapse_cost(pts, q, u, w))
    return best


@njit(cache=True, inline="always")
def _fan_from(j, n, n_loop, tris):
    """The triangles from loop position j over u's loop, into tris (loop positions, in
    the fan's orientation: fan triangle k, (u, k, k + 1), becomes (j, k, k + 1)); returns
    their count. Closed fans lose the two triangles on the edge u-j; open fans (j an end
    of the loop) the one."""
    ntri = 0
    for k in range(n):
        a, b = k, (k + 1) % n_loop
        if a == j or b == j:
            continue
        tris[ntri, 0], tris[ntri, 1], tris[ntri, 2] = j, a, b
        ntri += 1
    return ntri


@njit(cache=True, inline="always")
def _links(faces, vf, vdeg, loop, n_loop, closed, j):
    """The link condition for u -> loop[j]: no new edge from loop[j] already exists (the
    two vertices u and loop[j] share no neighbour but the ones across their edge)."""
    v = loop[j]
    for k in range(n_loop):
        gap = abs(k - j)
        if gap <= 1 or (closed and gap == n_loop - 1):
            continue
        if edge_exists(faces, vf, vdeg, v, loop[k]):
            return False
    return True


@njit(cache=True, inline="always")
def _upright(pts, loop, fn, tris, ntri):
    """Each new triangle neither degenerate nor turned over against the fan triangle it
    replaces (tris[t, 1] is that triangle's position in the fan)."""
    for t in range(ntri):
        a, b, c = loop[tris[t, 0]], loop[tris[t, 1]], loop[tris[t, 2]]
        ux, uy, uz = pts[b, 0] - pts[a, 0], pts[b, 1] - pts[a, 1], pts[b, 2] - pts[a, 2]
        wx, wy, wz = pts[c, 0] - pts[a, 0], pts[c, 1] - pts[a, 1], pts[c, 2] - pts[a, 2]
        cx, cy, cz = cross(ux, uy, uz, wx, wy, wz)
        k = tris[t, 1]
        if cx * fn[k, 0] + cy * fn[k, 1] + cz * fn[k, 2] <= 0.0:
            return False
        tx, ty, tz = wx - ux, wy - uy, wz - uz
        longest = max(
            ux * ux + uy * uy + uz * uz, wx * wx + wy * wy + wz * wz, tx * tx + ty * ty + tz * tz
        )
        if math.sqrt(cx * cx + cy * cy + cz * cz) <= _DEGENERATE * longest:
            return False
    return True


@njit(cache=True, inline="always")
def _candidates(pts, q, u, loop, n_loop, closed, costs, order):
    """Loop positions u may collapse to (all, or a boundary fan's two ends), cheapest
    first, into order; returns their count."""
    m = 0
    for k in range(n_loop):
        if closed or k == 0 or k == n_loop - 1:
            c = _collapse_cost(pts, q, u, loop[k])
            i = m
            while i > 0 and costs[i - 1] > c:  # insertion: a dozen entries at most
                costs[i], order[i] = costs[i - 1], order[i - 1]
                i -= 1
            costs[i], order[i] = c, k
            m += 1
    return m


@njit(cache=True, inline="always")
def _try_collapse(u, pts, faces, alive, vf, vdeg, q, terr, bound, scratch_i, scratch_f):
    """Collapse u into the cheapest neighbour whose collapse is valid and within ``bound``
    (mm, the new triangles' accumulated error); returns (triangles freed, loop length) or
    (-1, 0). The loop (scratch_i[1]) is u's old loop, whose vertices' fans changed."""
    fan, loop, a_s, b_s, tris, order = scratch_i
    fn, nrm, xyh, costs = scratch_f
    n = vdeg[u]
    n_loop, closed = order_fan(u, faces, vf, vdeg, fan, loop, a_s, b_s)
    if n_loop < 0 or (closed and n < 3) or (not closed and n < 2):
        return -1, 0
    if closed and n == 3 and face_exists(faces, vf, vdeg, loop[0], loop[1], loop[2]):
        return -1, 0  # u tops a tetrahedron: its base would be there twice
    carried = 0.0
    for k in range(n):
        carried = max(carried, terr[fan[k]])
    if carried >= bound:
        return -1, 0
    fan_normals(pts, faces, fan, n, fn)
    m = _candidates(pts, q, u, loop, n_loop, closed, costs, order)
    for i in range(m):
        j = order[i]
        if not _links(faces, vf, vdeg, loop, n_loop, closed, j):
            continue
        ntri = _fan_from(j, n, n_loop, tris)
        if not _upright(pts, loop, fn, tris, ntri):
            continue
        spent = carried + overlay_gap(
            pts, u, fn, n, loop, n_loop, tris, ntri, nrm, xyh, bound - carried
        )
        if spent > bound:
            continue
        if not commit(u, faces, alive, vf, vdeg, fan, n, loop, n_loop, tris, ntri, a_s):
            continue
        for t in range(ntri):
            terr[fan[t]] = spent
        v = loop[j]
        for k in range(10):
            q[v, k] += q[u, k]
        return n - ntri, n_loop
    return -1, 0


@njit(cache=True)
def _seed(pts, faces, vf, vdeg, q, locked, stamp):
    """A heap of (cost, vertex, stamp) for every vertex in use and not locked."""
    heap = [(np.inf, -1, -1)]
    heap.pop()
    for u in range(len(pts)):
        if vdeg[u] > 0 and not locked[u]:
            heap.append((_vertex_cost(pts, faces, vf, vdeg, q, u), u, stamp[u]))
    heapq.heapify(heap)
    return heap


@njit(cache=True, nogil=True)
def collapse_run(pts, faces, locked, bounds, target, min_cap):
    """Collapse ``faces`` (edited in place) cheapest first until at most ``target`` live
    triangles remain or no collapse is within the bound; each stage's bound (mm, rising)
    in turn. Returns (alive (F,) bool, live triangles, the last stage's bound mm)."""
    vf, vdeg = vertex_faces(faces, len(pts), min_cap)
    cap = vf.shape[1]
    q = plane_quadrics(pts, faces)
    alive = np.ones(len(faces), np.bool_)
    terr = np.zeros(len(faces))
    stamp = np.zeros(len(pts), np.int64)
    scratch_i = (
        np.zeros(cap, np.int32),
        np.zeros(cap + 1, np.int32),
        np.zeros(cap + 1, np.int32),
        np.zeros(cap, np.int32),
        np.zeros((cap, 3), np.int32),
        np.zeros(cap + 1, np.int32),
    )
    scratch_f = (np.zeros((cap, 3)), np.zeros(3), np.zeros((cap + 1, 3)), np.zeros(cap + 1))
    loop = scratch_i[1]
    n_alive = len(faces)
    bound = 0.0
    for s in range(len(bounds)):
        bound = bounds[s]
        heap = _seed(pts, faces, vf, vdeg, q, locked, stamp)
        while len(heap) > 0 and n_alive > target:
            _, u, st = heapq.heappop(heap)
            if st != stamp[u] or vdeg[u] == 0:
                continue  # stale: its fan changed since
            freed, n_loop = _try_collapse(
                u, pts, faces, alive, vf, vdeg, q, terr, bound, scratch_i, scratch_f
            )
            if freed < 0:
                continue  # back on the heap when its fan changes
            n_alive -= freed
            for t in range(n_loop):
                w = loop[t]
                stamp[w] += 1
                if not locked[w]:
                    cost = _vertex_cost(pts, faces, vf, vdeg, q, w)
                    heapq.heappush(heap, (cost, np.int64(w), stamp[w]))
        if n_alive <= target:
            break
    return alive, n_alive, bound
