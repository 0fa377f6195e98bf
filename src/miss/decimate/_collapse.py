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
vertex that stays), from a heap, instead of index order; and a vertex goes to the first
of its cheapest neighbours (``_CANDIDATES``) whose collapse is valid and within the bound.

A collapse is refused when it would change the topology (the link condition: a new edge
from v that already exists, or a vertex of valence 3 that tops a tetrahedron), turn a
triangle over or make one degenerate, leave a row of the vertex -> face table over its
capacity, or cost more than the bound. A boundary vertex goes only to a neighbour along
the boundary. Vertices never move and none are created: the output indexes the input's
vertex array.
"""

from __future__ import annotations

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
)
from miss.measure.distance import NO_REFCOUNT

# Largest number of triangles a vertex may carry (as vertex removal's _VALENCE_CAP).
_VALENCE_CAP = 32
# The cheapest neighbours a vertex may collapse into (by quadric cost) that are weighed:
# on CThead bone at 0.002, two took 11 % less time than all for 0.5 % more triangles.
_CANDIDATES = 2
# New triangles with 2 x area below this fraction of the squared longest edge are degenerate.
_DEGENERATE = 1e-6


@njit(cache=True)
def plane_quadrics(pts, faces):
    """(N, 11) area-weighted plane quadrics of each vertex's triangles (Garland & Heckbert):
    the upper triangle of [n n^T, n d; n d, d^2], per triangle plane n . x + d = 0, times
    its area (mm^2), summed into its three corners; and in column 10 each vertex's own
    quadric at itself (0: its planes pass through it), kept so that a collapse's cost
    reads one number of the vertex it goes to, not its whole quadric."""
    q = np.zeros((len(pts), 11))
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
    return _quadric_at(q, u, pts[v, 0], pts[v, 1], pts[v, 2]) + q[v, 10]


@njit(cache=True, **NO_REFCOUNT)
def _vertex_cost(pts, faces, vf, vdeg, q, u):
    """The heap's key for u: the least cost of collapsing u into a neighbour, each taken
    once as the corner after u in one of its triangles (in a boundary fan one end is
    left out: a key only orders, the collapse itself weighs them all). inf: none."""
    best = np.inf
    for k in range(vdeg[u]):
        f = vf[u, k]
        w = faces[f, 1] if faces[f, 0] == u else (faces[f, 2] if faces[f, 1] == u else faces[f, 0])
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
    (mm, the new triangles' accumulated error). Returns (triangles freed, loop length,
    0.0), the loop (scratch_i[1]) being u's old one, whose vertices' fans changed; or
    (-1, 0, the least bound under which one of the collapses weighed could go while u's
    fan stays as it is: inf where none could)."""
    fan, loop, a_s, b_s, tris, order = scratch_i
    fn, nrm, xyh, costs = scratch_f
    n = vdeg[u]
    n_loop, closed = order_fan(u, faces, vf, vdeg, fan, loop, a_s, b_s)
    if n_loop < 0 or (closed and n < 3) or (not closed and n < 2):
        return -1, 0, np.inf
    if closed and n == 3 and face_exists(faces, vf, vdeg, loop[0], loop[1], loop[2]):
        return -1, 0, np.inf  # u tops a tetrahedron: its base would be there twice
    carried = 0.0
    for k in range(n):
        carried = max(carried, terr[fan[k]])
    if carried >= bound:
        return -1, 0, carried
    fan_normals(pts, faces, fan, n, fn)
    m = _candidates(pts, q, u, loop, n_loop, closed, costs, order)
    need = np.inf
    for i in range(min(m, _CANDIDATES)):
        j = order[i]
        if not _links(faces, vf, vdeg, loop, n_loop, closed, j):
            continue
        ntri = _fan_from(j, n, n_loop, tris)
        if not _upright(pts, loop, fn, tris, ntri):
            continue
        # at most the least need so far: past it, this one is no better
        spent = carried + overlay_gap(
            pts, u, fn, n, loop, n_loop, tris, ntri, nrm, xyh, bound - carried
        )
        if spent > bound:
            need = min(need, spent)
            continue
        if not commit(u, faces, alive, vf, vdeg, fan, n, loop, n_loop, tris, ntri, a_s):
            need = min(need, spent)  # a row of the table is full: tried again next stage
            continue
        for t in range(ntri):
            terr[fan[t]] = spent
        v = loop[j]
        q[v, 10] = _collapse_cost(pts, q, u, v)
        for k in range(10):
            q[v, k] += q[u, k]
        return n - ntri, n_loop, 0.0
    return -1, 0, need


# --------------------------------------------------------------------------- the heap
# One entry per vertex (key: its least collapse cost), so that an update moves it rather
# than leaving a stale copy: arrays, no allocation (see _collapse_loop).


@njit(cache=True, inline="always")
def _swap(key, item, pos, i, j):
    key[i], key[j] = key[j], key[i]
    item[i], item[j] = item[j], item[i]
    pos[item[i]] = i
    pos[item[j]] = j


@njit(cache=True, **NO_REFCOUNT)
def _sift(key, item, pos, i, size):
    """Move entry i up or down to its place in the heap of ``size`` entries."""
    while i > 0 and key[(i - 1) >> 1] > key[i]:
        _swap(key, item, pos, i, (i - 1) >> 1)
        i = (i - 1) >> 1
    while True:
        c = 2 * i + 1
        if c >= size:
            return
        if c + 1 < size and key[c + 1] < key[c]:
            c += 1
        if key[i] <= key[c]:
            return
        _swap(key, item, pos, i, c)
        i = c


@njit(cache=True, **NO_REFCOUNT)
def _put(key, item, pos, size, v, cost):
    """Vertex v into the heap at ``cost``, or moved there; returns the heap's size."""
    i = pos[v]
    if i < 0:
        i = size
        size += 1
        item[i] = v
        pos[v] = i
    key[i] = cost
    _sift(key, item, pos, i, size)
    return size


@njit(cache=True, **NO_REFCOUNT)
def _pop(key, item, pos, size):
    """The cheapest vertex, out of the heap; returns (it, the heap's size)."""
    v = item[0]
    size -= 1
    if size > 0:
        _swap(key, item, pos, 0, size)
        _sift(key, item, pos, 0, size)
    pos[v] = -1
    return v, size


# --------------------------------------------------------------------------- the run


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def collapse_stage(
    pts, faces, alive, vf, vdeg, q, terr, locked, bound, n_alive, target, visit, owner, me,
    heap, need, scratch,
):  # fmt: skip
    """One stage: the vertices of ``visit`` that may go at ``bound`` (mm) collapsed cheapest
    first, and the vertices their collapses change, while ``owner`` of them is ``me``,
    until ``target`` live triangles remain or nothing more goes. Returns the live
    triangles. ``heap`` (key, item, pos) starts and ends empty; ``need`` (N,): each
    vertex's least bound, cached until its fan changes (0: unknown). Allocates nothing,
    so numba's reference counting is left out, and holds no lock: slabs whose vertices
    share no neighbour (see :func:`miss.decimate._fan.domains`) run side by side."""
    key, item, pos = heap
    scratch_i, scratch_f = scratch
    loop = scratch_i[1]
    size = 0
    for i in range(len(visit)):
        u = visit[i]
        if vdeg[u] > 0 and not locked[u] and pos[u] < 0 and need[u] <= bound:
            size = _put(key, item, pos, size, u, _vertex_cost(pts, faces, vf, vdeg, q, u))
    while size > 0 and n_alive > target:
        u, size = _pop(key, item, pos, size)
        freed, n_loop, needed = _try_collapse(
            u, pts, faces, alive, vf, vdeg, q, terr, bound, scratch_i, scratch_f
        )
        if freed < 0:
            need[u] = needed  # out of the heap until its fan changes or the bound rises
            continue
        n_alive -= freed
        for t in range(n_loop):
            w = loop[t]
            need[w] = 0.0
            if not locked[w] and owner[w] == me:
                size = _put(key, item, pos, size, w, _vertex_cost(pts, faces, vf, vdeg, q, w))
    for i in range(size):
        pos[item[i]] = -1
    return n_alive


@njit(cache=True)
def scratch(cap):
    """One thread's scratch for :func:`collapse_stage`, for fans of up to ``cap`` triangles."""
    scratch_i = (
        np.zeros(cap, np.int32),
        np.zeros(cap + 1, np.int32),
        np.zeros(cap + 1, np.int32),
        np.zeros(cap, np.int32),
        np.zeros((cap, 3), np.int32),
        np.zeros(cap + 1, np.int32),
    )
    return scratch_i, (np.zeros((cap, 3)), np.zeros(3), np.zeros((cap + 1, 3)), np.zeros(cap + 1))
