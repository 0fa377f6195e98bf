"""Vertex decimation after Schroeder, Zarge & Lorensen, "Decimation of triangle meshes" (1992).

This is step 4 of the MISS pipeline. Each vertex is classified from its fan of triangles
(simple, boundary, interior edge, corner, complex); a deletable vertex whose distance to its
average plane (simple) or to the line through its two edge neighbours (boundary, interior edge)
is within the bound is removed and its hole re-triangulated by recursive loop splitting.
Vertices are never moved and none is created; a vertex whose hole cannot be re-triangulated
without a degenerate, flipped or duplicated triangle or edge stays, so the topology (closedness,
Euler characteristic) is preserved. As in the paper, a vertex with one or more than two feature
edges (dihedral angle above ``feature_angle``) is a corner and stays; so does a boundary vertex
on a crease.

Iteration, as the implementations of the time did it (vtkDecimate): one pass over all vertices
in index order with the current bound; while the target triangle count is not reached the bound
is doubled (a zero bound steps to max_error / 8), clamped to ``max_error`` (default 10 x the
initial bound, i.e. five passes: b, 2b, 4b, 8b, 10b), and another pass is made. Passes at
``max_error`` repeat until one removes nothing, so the target may be missed. The run stops as
soon as the target is reached, even mid-pass. A vertex rejected for its distance keeps that
distance as the bound it needs, until a neighbour's deletion changes its fan, so later passes
only look at vertices that may now go.

Deletion is refused when the hole cannot be re-triangulated (no split with every loop vertex
strictly on its side of the split plane and an aspect ratio of at least ``_MIN_ASPECT``), when
a new triangle would be degenerate or face against the average plane, when a split line or a
boundary chord is already an edge (a third triangle on an edge, or a closed hole), when a
valence-3 vertex tops a tetrahedron, and when an ear's removal would drop a whole component.
The criterion is local, as in the paper: each deletion is measured against the current, already
decimated surface, so the distance to the original surface can exceed the bound.

Data structure: the face array is edited in place. Re-triangulating a fan of n triangles gives
n - 2 (closed fan) or n - 1 (boundary fan) triangles, which are written into the slots of the
removed ones; the spare slots are marked dead. Vertex -> face adjacency is a fixed-capacity
table (one row per vertex, ``_VALENCE_CAP`` or the input's largest valence if more); a deletion
that would overflow a row is refused, which plays the role of vtkDecimate's ``Degree`` limit.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from miss._numba import njit
from miss.decimate._fan import (
    commit,
    cross,
    domains,
    edge_exists,
    face_exists,
    fan_normals,
    frame,
    order_fan,
    overlay_gap,
    slabs,
    unit_normal_sum,
    vertex_faces,
    warm_sphere,
)
from miss.measure.distance import NO_REFCOUNT
from miss.types import column_bounds

SIMPLE, BOUNDARY, INTERIOR_EDGE, CORNER, COMPLEX = 0, 1, 2, 3, 4

# Largest number of triangles a vertex may carry after a deletion (vtkDecimate's Degree was 25).
_VALENCE_CAP = 32
# A split is accepted only if every loop vertex is at least this fraction of the split length
# away from the split plane; this keeps new triangles from being slivers.
_MIN_ASPECT = 1e-2
# New triangles with 2 x area below this fraction of the squared longest edge count as degenerate.
_DEGENERATE = 1e-6
# Distances below this fraction of the bounding-box diagonal are round-off.
_ROUND_OFF = 1e-12
# Bound schedule: multiply by this factor each pass; default max_error is this many initial bounds.
_BOUND_STEP = 2.0
_MAX_ERROR_FACTOR = 10.0
# A run takes one slab (see miss.decimate._fan.domains) per this many triangles, up to _MAX_SLABS slabs.
_SLAB_FACES = 65_536
_MAX_SLABS = 4


# The per-vertex steps are inlined into the pass loop at Numba IR level (inline="always"):
# passing a dozen arrays to a non-inlined call costs more than the work done in it, and this
# saves about a fifth of the run time. The split search stays a call to keep compile time low.
#
# The pass loop and the helpers it calls are compiled without numba's reference counting
# (:data:`miss.measure.distance.NO_REFCOUNT`): they allocate nothing, and every array they take,
# unpack or index as a row (``pts[i]``) had its count raised and lowered with an atomic
# instruction each time; on slabs run side by side (see miss.decimate._fan.domains) both cores wrote those
# counts' cache lines. perf put a fifth of a serial run in NRT_incref/NRT_decref. Without
# them: the same triangles, 1.88 -> 1.50 s serial and 1.10 -> 0.92 s in slabs on 2 cores
# (the paper's volume, bone, 0.002). ``_decimate_pass`` keeps counting: it allocates the
# scratch the loop uses.

# --------------------------------------------------------------------------- small geometry


@njit(cache=True, **NO_REFCOUNT)
def _edge_use(faces, vf, vdeg, a, b):
    """Number of live triangles holding both a and b."""
    count = 0
    for k in range(vdeg[a]):
        f = vf[a, k]
        if faces[f, 0] == b or faces[f, 1] == b or faces[f, 2] == b:
            count += 1
    return count


@njit(cache=True, **NO_REFCOUNT)
def _line_distance(pts, p, a, b):
    """Distance (mm) of point p from the line through points a and b; -1 if a == b."""
    ux = pts[b, 0] - pts[a, 0]
    uy = pts[b, 1] - pts[a, 1]
    uz = pts[b, 2] - pts[a, 2]
    length = math.sqrt(ux * ux + uy * uy + uz * uz)
    if length == 0.0:
        return -1.0
    cx, cy, cz = cross(
        pts[p, 0] - pts[a, 0], pts[p, 1] - pts[a, 1], pts[p, 2] - pts[a, 2], ux, uy, uz
    )
    return math.sqrt(cx * cx + cy * cy + cz * cz) / length


# --------------------------------------------------------------------------- classification


@njit(cache=True, **NO_REFCOUNT)
def _is_feature(fn, i, j, feature_cos):
    """Dihedral angle between fan triangles i and j above the feature angle."""
    d = fn[i, 0] * fn[j, 0] + fn[i, 1] * fn[j, 1] + fn[i, 2] * fn[j, 2]
    li = fn[i, 0] ** 2 + fn[i, 1] ** 2 + fn[i, 2] ** 2
    lj = fn[j, 0] ** 2 + fn[j, 1] ** 2 + fn[j, 2] ** 2
    # A zero-area triangle has no direction, so it cannot make a crease.
    if li == 0.0 or lj == 0.0:
        return False
    return d < feature_cos * math.sqrt(li * lj)


@njit(cache=True, inline="always")
def _classify(fn, n, closed, feature_cos):
    """Vertex type from its fan; returns (type, p, q), p < q the loop positions of the feature
    edges of an interior-edge vertex."""
    count = 0
    p = -1
    q = -1
    first = 0 if closed else 1
    for k in range(first, n):
        prev = k - 1 if k > 0 else n - 1
        if _is_feature(fn, prev, k, feature_cos):
            count += 1
            if p == -1:
                p = k
            else:
                q = k
    if not closed:
        # A boundary vertex on a crease is kept, as a corner, to keep the crease's end.
        return (BOUNDARY if count == 0 else CORNER), 0, n
    if count == 0:
        return SIMPLE, -1, -1
    if count == 2:
        return INTERIOR_EDGE, p, q
    return CORNER, -1, -1


@njit(cache=True, inline="always")
def _plane_distance(pts, faces, fan, n, fn, v):
    """Distance (mm) of v from its average plane: normal sum of area-weighted triangle normals,
    through the area-weighted triangle centres; -1 when the fan has no area."""
    nx = ny = nz = 0.0
    cx = cy = cz = 0.0
    area = 0.0
    for k in range(n):
        nx += fn[k, 0]
        ny += fn[k, 1]
        nz += fn[k, 2]
        w = math.sqrt(fn[k, 0] ** 2 + fn[k, 1] ** 2 + fn[k, 2] ** 2)
        f = fan[k]
        for c in range(3):
            u = faces[f, c]
            cx += w * pts[u, 0]
            cy += w * pts[u, 1]
            cz += w * pts[u, 2]
        area += 3.0 * w
    length = math.sqrt(nx * nx + ny * ny + nz * nz)
    if length == 0.0 or area == 0.0:
        return -1.0
    dx = pts[v, 0] - cx / area
    dy = pts[v, 1] - cy / area
    dz = pts[v, 2] - cz / area
    return abs(nx * dx + ny * dy + nz * dz) / length


# --------------------------------------------------------------------------- loop splitting


@njit(cache=True, **NO_REFCOUNT)
def _project_loop(pts, loop, n_loop, nrm, xyh):
    """Coordinates of the loop vertices in the frame of the unit normal nrm: (x, y) in the
    average plane (right-handed about nrm, so the loop runs counter-clockwise) and the height
    h along nrm, into xyh (n_loop, 3). Split planes are perpendicular to the average plane, so
    every side test becomes a 2-D cross product on (x, y)."""
    nx, ny, nz = nrm[0], nrm[1], nrm[2]
    ex, ey, ez, fx, fy, fz = frame(nx, ny, nz)
    for k in range(n_loop):
        u = loop[k]
        xyh[k, 0] = ex * pts[u, 0] + ey * pts[u, 1] + ez * pts[u, 2]
        xyh[k, 1] = fx * pts[u, 0] + fy * pts[u, 1] + fz * pts[u, 2]
        xyh[k, 2] = nx * pts[u, 0] + ny * pts[u, 1] + nz * pts[u, 2]


@njit(cache=True, **NO_REFCOUNT)
def _good_triangle(pts, a, b, c, nrm):
    """Non-degenerate and facing the same way as the average plane normal nrm."""
    ux, uy, uz = pts[b, 0] - pts[a, 0], pts[b, 1] - pts[a, 1], pts[b, 2] - pts[a, 2]
    wx, wy, wz = pts[c, 0] - pts[a, 0], pts[c, 1] - pts[a, 1], pts[c, 2] - pts[a, 2]
    cx, cy, cz = cross(ux, uy, uz, wx, wy, wz)
    if cx * nrm[0] + cy * nrm[1] + cz * nrm[2] <= 0.0:
        return False
    tx, ty, tz = pts[c, 0] - pts[b, 0], pts[c, 1] - pts[b, 1], pts[c, 2] - pts[b, 2]
    longest = max(
        ux * ux + uy * uy + uz * uz, wx * wx + wy * wy + wz * wz, tx * tx + ty * ty + tz * tz
    )
    return math.sqrt(cx * cx + cy * cy + cz * cz) > _DEGENERATE * longest


@njit(cache=True, **NO_REFCOUNT)
def _split_side(xyh, buf, s, first, last, ax, ay, dx, dy, sign, limit2, worst):
    """Smallest signed distance (times |d_plane|) of loop vertices first .. last-1 to the split
    plane, or -1 as soon as one is on the wrong side or no farther than sqrt(limit2)."""
    for k in range(first, last):
        pk = buf[s + k]
        dist = sign * (dy * (xyh[pk, 0] - ax) - dx * (xyh[pk, 1] - ay))
        if dist <= 0.0 or dist * dist <= limit2:
            return -1.0
        worst = min(worst, dist)
    return worst


@njit(cache=True, **NO_REFCOUNT)
def _best_split(xyh, loop, faces, vf, vdeg, buf, s, m, check_edges):
    """Best split (i, j), i < j, of the loop buf[s:s+m] (positions into xyh and loop), or (-1, -1).

    The split plane holds the split line and is perpendicular to the average plane. A split is
    valid when the loop vertices between i and j lie strictly on one side and the others on the
    other side; the best valid split has the largest aspect ratio (smallest distance of a loop
    vertex to the plane over the split length), at least _MIN_ASPECT. A split line that already
    is a mesh edge would give that edge a third triangle, so it is not valid; that look-up is
    costly and rarely true, so it is only made with check_edges (see _split_loop).

    Splits are tried from the widest span down because those usually have the best aspect,
    which lets the side test give up early on the rest; aspect ratios are compared squared to
    keep square roots out of this, the hottest loop.
    """
    best2 = _MIN_ASPECT * _MIN_ASPECT
    bi = -1
    bj = -1
    for span in range(m // 2, 1, -1):
        count = m // 2 if 2 * span == m else m
        for start in range(count):
            end = start + span
            i, j = (start, end) if end < m else (end - m, start)
            pa = buf[s + i]
            pb = buf[s + j]
            ax, ay = xyh[pa, 0], xyh[pa, 1]
            dx, dy, dh = xyh[pb, 0] - ax, xyh[pb, 1] - ay, xyh[pb, 2] - xyh[pa, 2]
            # distance to the split plane = (dy * x - dx * y) / |d_plane|; aspect = that / |d|
            scale2 = (dx * dx + dy * dy) * (dx * dx + dy * dy + dh * dh)
            if scale2 == 0.0:
                continue
            limit2 = best2 * scale2
            # For a counter-clockwise loop, vertices i+1 .. j-1 lie on the positive side.
            worst = _split_side(xyh, buf, s, i + 1, j, ax, ay, dx, dy, 1.0, limit2, np.inf)
            if worst > 0.0:
                worst = _split_side(xyh, buf, s, j + 1, m, ax, ay, dx, dy, -1.0, limit2, worst)
            if worst > 0.0:
                worst = _split_side(xyh, buf, s, 0, i, ax, ay, dx, dy, -1.0, limit2, worst)
            if worst > 0.0 and not (
                check_edges and edge_exists(faces, vf, vdeg, loop[pa], loop[pb])
            ):
                best2 = worst * worst / scale2
                bi = i
                bj = j
    return bi, bj


@njit(cache=True, inline="always")
def _split_loop(pts, faces, vf, vdeg, loop, n_loop, buf, start, size, top, nrm, scratch, ntri):
    """Triangulate the loop buf[start:start+size] (positions into loop) by recursive splitting.

    Child loops are written to buf from position top on; new triangles (loop positions, in
    loop order, so with the fan's orientation) are appended to tris from row ntri. Returns
    (ntri, top), ntri = -1 when some loop has no valid split or a final triangle would be
    degenerate or flipped.
    """
    stack, tris, xyh = scratch
    _project_loop(pts, loop, n_loop, nrm, xyh)
    stack[0, 0] = start
    stack[0, 1] = size
    depth = 1
    while depth > 0:
        depth -= 1
        s = stack[depth, 0]
        m = stack[depth, 1]
        if m == 3:
            a, b, c = buf[s], buf[s + 1], buf[s + 2]
            if not _good_triangle(pts, loop[a], loop[b], loop[c], nrm):
                return -1, top
            tris[ntri, 0], tris[ntri, 1], tris[ntri, 2] = a, b, c
            ntri += 1
            continue
        i, j = _best_split(xyh, loop, faces, vf, vdeg, buf, s, m, False)
        if i >= 0 and edge_exists(faces, vf, vdeg, loop[buf[s + i]], loop[buf[s + j]]):
            i, j = _best_split(xyh, loop, faces, vf, vdeg, buf, s, m, True)
        if i < 0:
            return -1, top
        for k in range(i, j + 1):
            buf[top + k - i] = buf[s + k]
        stack[depth, 0] = top
        stack[depth, 1] = j - i + 1
        depth += 1
        top += j - i + 1
        c = 0
        for k in range(j, m):
            buf[top + c] = buf[s + k]
            c += 1
        for k in range(i + 1):
            buf[top + c] = buf[s + k]
            c += 1
        stack[depth, 0] = top
        stack[depth, 1] = c
        depth += 1
        top += c
    return ntri, top


@njit(cache=True, inline="always")
def _retriangulate(pts, faces, vf, vdeg, loop, n_loop, fn, n, vtype, p, q, buf, scratch, nrm):
    """Triangles that fill the hole of the deleted vertex into scratch's tris; returns their
    count or -1.

    Simple and boundary vertices leave one loop (a boundary loop is closed by the chord between
    its ends, which becomes a boundary edge). An interior-edge vertex leaves two loops: the
    feature edge between loop[p] and loop[q] is kept as the first split, and each half is split
    about the average plane of its own triangles so a crease is not flattened.
    """
    if vtype == INTERIOR_EDGE:
        na = q - p + 1
        nb = n - na + 2
        if na < 3 or nb < 3 or edge_exists(faces, vf, vdeg, loop[p], loop[q]):
            return -1
        for k in range(na):
            buf[k] = p + k
        for k in range(nb):
            buf[na + k] = (q + k) % n
        if not unit_normal_sum(fn, p, q, n, nrm):
            return -1
        ntri, top = _split_loop(
            pts, faces, vf, vdeg, loop, n_loop, buf, 0, na, na + nb, nrm, scratch, 0
        )
        if ntri < 0 or not unit_normal_sum(fn, q, n + p, n, nrm):
            return -1
        ntri, top = _split_loop(
            pts, faces, vf, vdeg, loop, n_loop, buf, na, nb, top, nrm, scratch, ntri
        )
        return ntri
    if vtype == BOUNDARY:
        a, b = loop[0], loop[n_loop - 1]
        if n_loop == 2:
            # Removing an ear: its opposite edge must stay shared, or a component vanishes.
            return 0 if _edge_use(faces, vf, vdeg, a, b) >= 2 else -1
        if edge_exists(faces, vf, vdeg, a, b):
            return -1
    elif n_loop < 3 or (n_loop == 3 and face_exists(faces, vf, vdeg, loop[0], loop[1], loop[2])):
        # A valence-3 vertex whose loop already is a triangle tops a tetrahedron: deleting it
        # would leave that triangle twice.
        return -1
    for k in range(n_loop):
        buf[k] = k
    if not unit_normal_sum(fn, 0, n, n, nrm):
        return -1
    ntri, top = _split_loop(
        pts, faces, vf, vdeg, loop, n_loop, buf, 0, n_loop, n_loop, nrm, scratch, 0
    )
    return ntri


# --------------------------------------------------------------------------- mesh update


@njit(cache=True, inline="always")
def _deletion_bound(v, pts, faces, vf, vdeg, feature_cos, scratch_i, scratch_f):
    """Classify v and return (distance in mm, type, p, q, n_loop); distance is inf when v can
    never go while its fan stays as it is (complex, corner, no area). Fills fan, loop and fn."""
    fan, loop, a_s, b_s = scratch_i[0], scratch_i[1], scratch_i[2], scratch_i[3]
    fn = scratch_f[0]
    n = vdeg[v]
    n_loop, closed = order_fan(v, faces, vf, vdeg, fan, loop, a_s, b_s)
    if n_loop < 0:
        return np.inf, COMPLEX, -1, -1, n_loop
    fan_normals(pts, faces, fan, n, fn)
    vtype, p, q = _classify(fn, n, closed, feature_cos)
    if vtype == CORNER:
        return np.inf, vtype, p, q, n_loop
    if vtype == SIMPLE:
        d = _plane_distance(pts, faces, fan, n, fn, v)
    else:
        d = _line_distance(pts, v, loop[p], loop[q if vtype == INTERIOR_EDGE else n_loop - 1])
    return (np.inf if d < 0.0 else d), vtype, p, q, n_loop


@njit(cache=True, inline="always")
def _try_delete(
    v, pts, faces, alive, vf, vdeg, bound, feature_cos, scratch_i, scratch_f, vmin, terr
):
    """Delete vertex v if its type and distance allow it and its hole can be re-triangulated.

    Returns the number of triangles freed (2 for a closed fan, 1 for a boundary fan) or -1.
    vmin caches, per vertex, the smallest bound (mm) under which it could go while its fan
    stays as it is (inf: never); 0 means unknown. A refusal because a neighbour's row is full
    is not cached, since it depends on more than v's fan.

    ``terr`` (per face slot, mm) is the accumulated error, or has length 0 for the paper's
    local criterion. With it, each triangle carries the deviation already spent on it: v goes
    only if its distance plus the most its fan carries, and the fan-to-patch deviation plus
    that, are within the bound; the new triangles then carry the latter.
    """
    fan, loop, a_s, b_s, buf, stack, tris = scratch_i
    fn, nrm, xyh = scratch_f
    n = vdeg[v]
    d, vtype, p, q, n_loop = _deletion_bound(
        v, pts, faces, vf, vdeg, feature_cos, scratch_i, scratch_f
    )
    carried = 0.0
    if len(terr) > 0:
        for k in range(n):
            carried = max(carried, terr[fan[k]])
    if d + carried > bound:
        vmin[v] = d + carried
        return -1
    scratch = (stack, tris, xyh)
    ntri = _retriangulate(pts, faces, vf, vdeg, loop, n_loop, fn, n, vtype, p, q, buf, scratch, nrm)
    if ntri < 0:
        vmin[v] = np.inf
        return -1
    spent = 0.0
    if len(terr) > 0:
        # nrm and xyh, the split's, are free once the hole is filled
        spent = carried + overlay_gap(
            pts, v, fn, n, loop, n_loop, tris, ntri, nrm, xyh, bound - carried
        )
        if spent > bound:
            vmin[v] = spent
            return -1
    if not commit(v, faces, alive, vf, vdeg, fan, n, loop, n_loop, tris, ntri, a_s):
        return -1
    if len(terr) > 0:
        for t in range(ntri):
            terr[fan[t]] = spent
    for t in range(n_loop):
        vmin[loop[t]] = 0.0  # their fans changed
    return n - ntri


@njit(cache=True, nogil=True)
def _decimate_pass(
    pts, faces, alive, vf, vdeg, bound, feature_cos, n_alive, target, vmin, terr, locked, visit
):
    """One pass over the vertices ``visit`` (in that order); stops once n_alive <= target.

    Vertices whose cached vmin (see _try_delete) exceeds the bound are skipped, so a pass with
    a raised bound only looks again at the vertices it might now delete. Without the GIL:
    passes over vertex sets that share no neighbour run side by side (see miss.decimate._fan.domains).
    Returns (n_alive, vertices removed in this pass).
    """
    cap = vf.shape[1]
    # Scratch sized for the largest fan, allocated once per pass rather than per vertex.
    scratch_i = (
        np.zeros(cap, np.int32),
        np.zeros(cap + 1, np.int32),
        np.zeros(cap + 1, np.int32),  # also counts per loop position in commit
        np.zeros(cap, np.int32),
        np.zeros(2 * (cap + 4) ** 2, np.int32),
        np.zeros((2 * cap + 8, 2), np.int32),
        np.zeros((cap, 3), np.int32),
    )
    scratch_f = (np.zeros((cap, 3)), np.zeros(3), np.zeros((cap + 1, 3)))
    # the loop, without reference counting (see the note at the top of the kernels)
    return _pass_loop(
        pts, faces, alive, vf, vdeg, bound, feature_cos, n_alive, target, vmin, terr, locked,
        visit, scratch_i, scratch_f,
    )  # fmt: skip


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _pass_loop(
    pts, faces, alive, vf, vdeg, bound, feature_cos, n_alive, target, vmin, terr, locked,
    visit, scratch_i, scratch_f,
):  # fmt: skip
    """The loop of :func:`_decimate_pass` over ``visit``, with its scratch; allocates
    nothing, so numba's reference counting is left out of it and of what it calls."""
    removed = 0
    for i in range(len(visit)):
        if n_alive <= target:
            break
        v = visit[i]
        if vdeg[v] == 0 or vmin[v] > bound or locked[v]:
            continue
        freed = _try_delete(
            v, pts, faces, alive, vf, vdeg, bound, feature_cos, scratch_i, scratch_f, vmin, terr
        )
        if freed >= 0:
            n_alive -= freed
            removed += 1
    return n_alive, removed


# --------------------------------------------------------------------------- public API


def _check_inputs(
    vertices: np.ndarray, faces: np.ndarray, reduce: float, error_bound: float, max_error
) -> None:
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must have shape (N, 3); got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"faces must be an (F, 3) integer array; got {faces.shape} {faces.dtype}")
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(
            "faces index vertices out of range; pass the vertex array the faces refer to"
        )
    if np.any(
        (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    ):
        raise ValueError("faces repeat a vertex; drop index-degenerate triangles before decimating")
    if not 0.0 <= reduce < 1.0:
        raise ValueError(f"reduce is the fraction of triangles to remove, in [0, 1); got {reduce}")
    if not error_bound >= 0.0:
        raise ValueError(f"error_bound is a distance in mm and must be >= 0; got {error_bound}")
    if max_error is not None and not max_error >= 0.0:
        raise ValueError(f"max_error is a distance in mm and must be >= 0; got {max_error}")


def _slab_count(n_faces: int, whole_passes: int) -> int:
    """Slabs for a run (see miss.decimate._fan.domains): one per ``_SLAB_FACES`` triangles, a power of two up to
    ``_MAX_SLABS``; one (the plain serial run) under the paper's whole passes, which must
    visit every vertex in index order. Set by the mesh alone, not by the machine, so that the
    output is the same on any machine."""
    if whole_passes > 0:
        return 1
    count = 1
    while count < _MAX_SLABS and n_faces >= 2 * count * _SLAB_FACES:
        count *= 2
    return count


def _run_passes(
    pts, faces, target, error_bound, max_error, feature_cos, whole_passes, accumulate, locked,
    done=None,
):  # fmt: skip
    """Passes with a rising bound until n_alive <= target or a pass at max_error removes
    nothing. Edits faces in place; returns (alive mask, passes, last bound, vertices removed).

    A large mesh's passes run in slabs (see miss.decimate._fan.domains), side by side on up to as many threads
    as there are cores, each slab stopping at its share of the triangles to remove; then
    the same pass, serially, over the guard between the slabs. The slabs are set again
    before each pass, so every vertex meets every bound of the schedule.

    ``whole_passes`` > 0: the paper's schedule instead (vtkDecimate's iterations): at most that
    many passes at k x error_bound (k = 1, 2, ...), each run to its end; the target is
    looked at only between passes. ``accumulate``: triangles carry the error spent on them
    (see _try_delete); ``locked`` (N,) bool: vertices that stay. ``done(fraction)``, when
    given, hears after each pass the share of the triangles to remove that are gone."""
    alive = np.ones(len(faces), dtype=bool)
    heard = done or (lambda fraction: None)
    to_remove = max(len(faces) - target, 1)
    vf, vdeg = vertex_faces(faces, len(pts), _VALENCE_CAP)
    vmin = np.zeros(len(pts), dtype=np.float64)
    terr = np.zeros(len(faces) if accumulate else 0, dtype=np.float64)
    everything = np.arange(len(pts), dtype=np.int32)
    # Distances within round-off of zero count as zero, so a flat region goes at bound 0.
    slack = (
        _ROUND_OFF * float(np.linalg.norm(np.subtract(*column_bounds(pts)[::-1])))
        if len(pts)
        else 0.0
    )
    bound, n_alive, passes, removed_total = error_bound, len(faces), 0, 0

    def one_pass(limit: float, n: int, stop: int, visit: np.ndarray) -> tuple[int, int]:
        return _decimate_pass(
            pts, faces, alive, vf, vdeg, limit, feature_cos, n, stop, vmin, terr, locked, visit
        )

    if whole_passes > 0:
        for k in range(1, whole_passes + 1):
            bound = k * error_bound
            n_alive, removed = one_pass(bound + slack, n_alive, -1, everything)
            passes, removed_total = passes + 1, removed_total + removed
            heard(min(1.0, (len(faces) - n_alive) / to_remove))
            if n_alive <= target:
                break
        return alive, passes, bound, removed_total
    count = _slab_count(len(faces), whole_passes)
    slab = slabs(pts, faces, count) if count > 1 else None
    pool = (
        ThreadPoolExecutor(min(count, os.cpu_count() or 1), thread_name_prefix="miss-slab")
        if count > 1
        else None
    )
    try:
        while True:
            removed, visit = 0, everything
            if slab is not None and pool is not None:
                order, starts = domains(faces, alive, vdeg, slab, count)
                sizes = np.diff(starts[: count + 1]).astype(np.float64)
                # each slab stops at its share (by vertices) of the triangles to remove
                share = (n_alive - target) / max(sizes.sum(), 1.0)
                ends = [n_alive - math.floor(share * n) for n in sizes]
                runs = [
                    pool.submit(
                        one_pass, bound + slack, n_alive, ends[d], order[starts[d] : starts[d + 1]]
                    )
                    for d in range(count)
                ]
                done = [r.result() for r in runs]
                n_alive -= sum(n_alive - d[0] for d in done)
                removed, visit = sum(d[1] for d in done), order[starts[count] :]
            n_alive, more = one_pass(bound + slack, n_alive, target, visit)
            passes += 1
            removed += more
            removed_total += removed
            heard(min(1.0, (len(faces) - n_alive) / to_remove))
            if n_alive <= target or (bound >= max_error and removed == 0):
                return alive, passes, bound, removed_total
            # Doubling never leaves 0, so a zero bound steps to an eighth of max_error instead.
            bound = min(bound * _BOUND_STEP if bound > 0 else max_error / 8, max_error)
    finally:
        if pool is not None:
            pool.shutdown()


def schroeder_decimate(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    reduce: float,
    error_bound: float,
    max_error: float | None = None,
    feature_angle: float = 75.0,
    paper_passes: int = 0,
    accumulate: bool = True,
    locked: np.ndarray | None = None,
    done: Callable[[float], None] | None = None,
) -> tuple[np.ndarray, dict]:
    """Decimate a triangle mesh by vertex removal (Schroeder, Zarge & Lorensen 1992).

    Parameters
    ----------
    vertices : (N, 3) float array
        Vertex positions in mm. Never moved; the result indexes this same array.
    faces : (F, 3) int array
        Triangles, counter-clockwise seen from outside.
    reduce : float
        Target fraction of triangles to remove, in [0, 1) (0.9 keeps 10 %). The run stops as
        soon as it is met, even in the middle of a pass.
    error_bound : float
        Initial distance bound in mm (plane distance for simple vertices, line distance for
        boundary and interior-edge vertices). Doubled after each pass that misses the target.
    max_error : float, optional
        Largest bound in mm; default ``10 * error_bound``. Passes at this bound repeat until one
        removes nothing, so the target may be missed.
    feature_angle : float
        Dihedral angle in degrees above which an edge is a feature edge.
    paper_passes : int
        0 (default): the schedule above. N > 0: the 1998 pipeline's (VTK's ``vtkDecimate``
        iterations, its error increment equal to the initial bound): at most N whole passes
        at bounds 1, 2, ..., N x ``error_bound``, the target looked at only between passes,
        so a pass may overshoot it and the last may fall short; ``max_error`` is not used.
    accumulate : bool
        True (default): every triangle carries the deviation already spent on it (its
        fan's most, plus the deviation between the fan and the triangles that replace
        it), and a vertex goes only if that stays within the current bound, so the
        surface stays within ``final_bound_mm`` of the input however deletions chain
        (the refinement of the algorithm that ``vtkDecimatePro``'s ``AccumulateError``
        approximates). False: the paper's local criterion alone; deviations stack up.
    locked : (N,) bool array, optional
        Vertices that must stay (the caller's repair of a region measured out of bound).
    done : callable, optional
        ``done(fraction)`` after each pass: the share (0..1) of the triangles to remove that
        are gone, for a job's progress.

    Returns
    -------
    new_faces : (M, 3) int32 array
        Triangles indexing ``vertices``, orientation kept.
    info : dict
        ``passes``, ``final_bound_mm`` (the bound of the last pass), ``removed_vertices`` and
        ``reduction`` (fraction of triangles removed).
    """
    vertices = np.asarray(vertices)
    faces = np.asarray(faces)
    _check_inputs(vertices, faces, reduce, error_bound, max_error)
    error_bound = float(error_bound)
    max_error = _MAX_ERROR_FACTOR * error_bound if max_error is None else float(max_error)
    pts = np.ascontiguousarray(vertices, dtype=np.float64)
    work = np.array(faces, dtype=np.int32, order="C")  # a copy: edited in place
    # floor, so that meeting the target means info["reduction"] >= reduce
    target = math.floor(len(work) * (1.0 - reduce) + 1e-9)
    feature_cos = float(np.cos(np.radians(feature_angle)))
    if locked is None:
        locked = np.zeros(len(pts), dtype=np.bool_)
    elif locked.shape != (len(pts),):
        raise ValueError(f"locked must be an (N,) bool array, one per vertex; got {locked.shape}")
    alive, passes, bound, removed = _run_passes(
        pts, work, target, error_bound, max(max_error, error_bound), feature_cos, paper_passes,
        accumulate, np.ascontiguousarray(locked, dtype=np.bool_), done,
    )  # fmt: skip
    new_faces = work[alive]
    info = {
        "passes": passes,
        "final_bound_mm": bound,
        "removed_vertices": removed,
        "reduction": 1.0 - len(new_faces) / len(work) if len(work) else 0.0,
    }
    return new_faces, info


def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel once, on a small sphere.

    ``make`` calls this after installing so that tests and the server's worker
    processes load compiled code instead of racing to compile it at the same time.
    """
    pts, faces = warm_sphere()
    schroeder_decimate(pts, faces, reduce=0.5, error_bound=0.01)
