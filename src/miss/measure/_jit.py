"""Measured distance between two surfaces, in millimetres.

Used to report what a decimation really did, not just the bound it was given:
points are sampled on each surface (its vertices plus random points inside its
triangles) and their exact distance to the other surface is taken, both ways.

The distances are exact: triangles are binned into a uniform grid of cells about the median
edge long (by their bounding boxes), their corners copied side by side, a row a triangle.
Each query looks in its own cell first, then in rings of cells around it, skipping cells and
triangles whose box is farther than the best triangle so far, and stops once the best is
nearer than the outside of the searched block (Ericson's closest-point-on-triangle for each
candidate). Queries run in parallel (numba) grouped by blocks of cells, so neighbouring
queries share cached triangles, and write their answers in that order (points that come
in a mesh's order, as :func:`bound_check`'s and a deviation's on the undecimated surface
do, are neighbours already and go as they come). Zero-area triangles count by their edges;
checked against brute force in tests/test_deviation.py.

:func:`deviation` draws the same samples as :func:`sample_surface` (so the same figures) but
keeps them in vertex and triangle order, and makes one surface's grid in a second thread
while it samples the other (the decimated one's, when the undecimated one's half was made
while it was decimated: :func:`side_of`). The grid and the query order are what make the
exact search cheap enough to run after every job (``benchmarks/measure.py``).
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from miss._numba import njit, prange
from miss.measure._core import Deviation, Kernels, Side, half, measure
from miss.measure._core import grid_shape as _grid_shape
from miss.measure.distance import NO_REFCOUNT, triangle_sq
from miss.types import Mesh


def sample_surface(mesh: Mesh, count: int, rng: np.random.Generator) -> np.ndarray:
    """(count, 3) points: all vertices used by faces (subsampled if too many) plus area-weighted
    random points inside triangles, so both corners and flat interiors are checked."""
    return _sample(mesh, count, rng, drawn=True)


def _sample(mesh: Mesh, count: int, rng: np.random.Generator, drawn: bool) -> np.ndarray:
    """:func:`sample_surface`'s points, in the order drawn or (``drawn`` False) with the
    corners in vertex order and the inner points in triangle order: neighbours together,
    which the search for their distances reads faster."""
    used = np.flatnonzero(_used(mesh.faces, mesh.n_vertices))
    # choice(n) draws what choice(used) does (it takes used[those] after)
    chosen = rng.choice(len(used), size=min(len(used), count // 2), replace=False)
    if not drawn:  # the same vertices in increasing order, without a sort
        mark = np.zeros(len(used), dtype=bool)
        mark[chosen] = True
        chosen = np.flatnonzero(mark)
    corners = mesh.vertices[used[chosen]]
    n_inner = count - len(corners)
    cum = _cumulative_areas(mesh.vertices, mesh.faces)
    target = rng.random(n_inner) * cum[-1]
    order = _increasing(target, cum[-1])
    r1, r2 = rng.random(n_inner), rng.random(n_inner)
    out = np.empty((count, 3))
    out[: len(corners)] = corners
    slots = order if drawn else np.arange(n_inner)
    _inner_points(mesh.vertices, mesh.faces, cum, target, order, r1, r2, slots, out[len(corners) :])
    return out


@njit(cache=True, nogil=True)
def _used(faces, n):
    """(n,) bool: the vertices some face uses (a mask, not np.unique: no sort of 3 F indices)."""
    out = np.zeros(n, dtype=np.bool_)
    for f in range(len(faces)):
        for k in range(3):
            out[faces[f, k]] = True
    return out


@njit(cache=True, nogil=True)
def _increasing(values, top):
    """Indices that sort ``values`` (uniform in [0, top]): into a bucket each by value, then
    each bucket's few in order (a quarter of np.argsort's time for 100 000)."""
    n = len(values)
    scale = n / top if top > 0 else 0.0
    bucket = np.empty(n, dtype=np.int64)
    start = np.zeros(n + 1, dtype=np.int64)
    for i in range(n):
        bucket[i] = min(int(values[i] * scale), n - 1)
        start[bucket[i] + 1] += 1
    for b in range(1, n + 1):
        start[b] += start[b - 1]
    order = np.empty(n, dtype=np.int64)
    fill = start[:-1].copy()
    for i in range(n):
        order[fill[bucket[i]]] = i
        fill[bucket[i]] += 1
    for b in range(n):  # insertion sort: a bucket holds one or two as a rule
        for j in range(start[b] + 1, start[b + 1]):
            i, m = order[j], j
            while m > start[b] and values[order[m - 1]] > values[i]:
                order[m] = order[m - 1]
                m -= 1
            order[m] = i
    return order


@njit(cache=True, nogil=True)
def _cumulative_areas(verts, faces):
    """Running sum of twice the triangles' areas, float64 (what choice(p=) does underneath,
    without its O(F) checks)."""
    out = np.empty(len(faces))
    total = 0.0
    for f in range(len(faces)):
        a, b, c = verts[faces[f, 0]], verts[faces[f, 1]], verts[faces[f, 2]]
        # np.float64, not float(): numba's float() of a float32 is a float32
        ux, uy, uz = np.float64(b[0]) - a[0], np.float64(b[1]) - a[1], np.float64(b[2]) - a[2]
        vx, vy, vz = np.float64(c[0]) - a[0], np.float64(c[1]) - a[1], np.float64(c[2]) - a[2]
        nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
        total += math.sqrt(nx * nx + ny * ny + nz * nz)
        out[f] = total
    return out


@njit(cache=True, nogil=True)
def _inner_points(verts, faces, cum, target, order, r1, r2, slots, out):
    """out[slots[j]] = the point (r1, r2) of the triangle where target order[j] falls in the
    running sum ``cum``, folded back inside when r1 + r2 > 1. The targets taken in increasing
    order walk ``cum`` once (searchsorted's "right" triangle, the last for a target past it)."""
    f = 0
    for j in range(len(order)):
        i = order[j]
        while f < len(cum) - 1 and cum[f] <= target[i]:
            f += 1
        s, t = r1[i], r2[i]
        if s + t > 1:
            s, t = 1 - s, 1 - t
        a, b, c = verts[faces[f, 0]], verts[faces[f, 1]], verts[faces[f, 2]]
        for k in range(3):
            ak = np.float64(a[k])  # in float64 (see _cumulative_areas)
            out[slots[j], k] = ak + s * (np.float64(b[k]) - ak) + t * (np.float64(c[k]) - ak)


@njit(cache=True, nogil=True)
def _corners(verts, faces, lo, cell, dims, spans):
    """(F, 9) each triangle's corners a, b, c side by side, in the vertices' dtype: the search
    reads one row where it read three scattered vertices (its queries a third faster). Fills
    ``spans`` (F, 6): the first and last cell along x, y, z that each triangle's box meets.
    Serial: :func:`deviation` builds one grid in a thread of its own while it samples."""
    out = np.empty((len(faces), 9), dtype=verts.dtype)
    for f in range(len(faces)):
        for axis in range(3):
            a, b, c = verts[faces[f, 0], axis], verts[faces[f, 1], axis], verts[faces[f, 2], axis]
            out[f, axis], out[f, 3 + axis], out[f, 6 + axis] = a, b, c
            first = int((min(a, b, c) - lo[axis]) / cell)
            last = int((max(a, b, c) - lo[axis]) / cell)
            spans[f, axis] = max(0, min(first, dims[axis] - 1))
            spans[f, 3 + axis] = max(0, min(last, dims[axis] - 1))
    return out


@njit(cache=True, nogil=True)
def _build_grid(spans, dims):
    """CSR lists of the triangles whose bounding box meets each cell: (offsets, items).

    Two passes over the triangles' ``spans`` (count, then fill) instead of sorting (cell,
    triangle) pairs; the fill advances each cell's start, which moves back after.
    """
    offsets = np.zeros(dims[0] * dims[1] * dims[2] + 1, dtype=np.int32)
    items = np.empty(0, dtype=np.int32)
    for fill in (False, True):
        if fill:
            for c in range(1, len(offsets)):  # in place: np.cumsum would make an int64 copy
                offsets[c] += offsets[c - 1]
            items = np.empty(offsets[-1], dtype=np.int32)
        for f in range(len(spans)):
            for k in range(spans[f, 2], spans[f, 5] + 1):
                for j in range(spans[f, 1], spans[f, 4] + 1):
                    row = (k * dims[1] + j) * dims[0]
                    for c in range(row + spans[f, 0], row + spans[f, 3] + 1):
                        if fill:
                            items[offsets[c]] = f
                            offsets[c] += 1
                        else:
                            offsets[c + 1] += 1
    for c in range(len(offsets) - 1, 0, -1):  # each start had moved to the next one's
        offsets[c] = offsets[c - 1]
    offsets[0] = 0
    return offsets, items


@njit(cache=True, inline="always")
def _gap(v, idx, lo, cell):
    """Distance from coordinate v to the slab of cells ``idx`` that starts at lo (0 inside)."""
    return max(lo + idx * cell - v, v - lo - (idx + 1) * cell, 0.0)


@njit(cache=True, inline="always")
def _box_sq(p, low, high):
    """Squared distance from coordinate p to the interval [low, high]."""
    return max(low - p, p - high, 0.0) ** 2


@njit(cache=True, **NO_REFCOUNT)
def _cell_sq(px, py, pz, c, best, offsets, items, tri):
    """Smaller of ``best`` and the squared distance from p to the triangles listed in cell c."""
    for n in range(offsets[c], offsets[c + 1]):
        f = items[n]
        ax, ay, az = tri[f, 0], tri[f, 1], tri[f, 2]
        bx, by, bz = tri[f, 3], tri[f, 4], tri[f, 5]
        cx, cy, cz = tri[f, 6], tri[f, 7], tri[f, 8]
        # squared distance to the triangle's box: most are dismissed on that alone
        gap = _box_sq(px, min(ax, bx, cx), max(ax, bx, cx))
        gap += _box_sq(py, min(ay, by, cy), max(ay, by, cy))
        gap += _box_sq(pz, min(az, bz, cz), max(az, bz, cz))
        if gap < best:
            best = min(best, triangle_sq(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz))
            if best == 0.0:  # a vertex or a point of the surface itself: nothing is nearer
                break
    return best


@njit(cache=True, inline="always")
def _home(v, lo, cell, n):
    """The cell holding coordinate v along one axis of n cells, or the nearest one when v
    lies outside the grid."""
    return max(0, min(int((v - lo) / cell), n - 1))


@njit(cache=True, inline="always")
def _margin(v, h, r, lo, cell, n, m):
    """Smaller of m and the distance from coordinate v to the outside of the cells within r
    of cell h along one axis of n cells (m when they reach both ends: nothing is outside)."""
    if h - r > 0:
        m = min(m, v - (lo + (h - r) * cell))
    if h + r < n - 1:
        m = min(m, lo + (h + r + 1) * cell - v)
    return m


@njit(cache=True, **NO_REFCOUNT)
def _nearest_sq(px, py, pz, lox, loy, loz, cell, nx, ny, nz, offsets, items, tri, cap2):
    """Squared distance from p to the nearest triangle: its own cell first, then rings of
    cells around it, skipping cells whose box is farther than the best triangle so far, until
    the best is nearer than anything outside the searched block, or that block reaches
    farther than sqrt(cap2) (then the answer is only known to be above it: the best so far,
    inf if none). On coordinates and arrays, not tuples and rows: no array is counted (an
    atomic instruction on a header both threads share; 5 % of the search)."""
    hx, hy, hz = _home(px, lox, cell, nx), _home(py, loy, cell, ny), _home(pz, loz, cell, nz)
    best = _cell_sq(px, py, pz, (hz * ny + hy) * nx + hx, np.inf, offsets, items, tri)
    r = 0
    while True:
        m = _margin(px, hx, r, lox, cell, nx, np.inf)
        m = _margin(py, hy, r, loy, cell, ny, m)
        m = _margin(pz, hz, r, loz, cell, nz, m)
        if m == np.inf or best <= m * m or m * m > cap2:
            return best
        r += 1
        for k in range(max(hz - r, 0), min(hz + r, nz - 1) + 1):
            gk = _gap(pz, k, loz, cell) ** 2
            if gk >= best:
                continue
            for j in range(max(hy - r, 0), min(hy + r, ny - 1) + 1):
                gj = gk + _gap(py, j, loy, cell) ** 2
                if gj >= best:
                    continue
                # inside the block's shell only its two end cells along x are new
                step = 1 if abs(k - hz) == r or abs(j - hy) == r else 2 * r
                for i in range(hx - r, hx + r + 1, step):
                    if 0 <= i < nx:
                        g = gj + _gap(px, i, lox, cell) ** 2
                        if g < best:
                            c = (k * ny + j) * nx + i
                            best = _cell_sq(px, py, pz, c, best, offsets, items, tri)


@njit(cache=True, nogil=True)
def _block_order(points, lo, cell, dims, side=2):
    """The points in order of the block of side x side x side cells holding them (a counting
    sort): neighbouring queries read the same triangles, which then stay in cache."""
    bx, by = (dims[0] + side - 1) // side, (dims[1] + side - 1) // side
    bz = (dims[2] + side - 1) // side
    keys = np.empty(len(points), dtype=np.int64)
    start = np.zeros(bx * by * bz + 1, dtype=np.int64)
    for n in range(len(points)):
        hx = _home(points[n, 0], lo[0], cell, dims[0])
        hy = _home(points[n, 1], lo[1], cell, dims[1])
        hz = _home(points[n, 2], lo[2], cell, dims[2])
        keys[n] = ((hz // side) * by + hy // side) * bx + hx // side
        start[keys[n] + 1] += 1
    for c in range(1, len(start)):
        start[c] += start[c - 1]
    order = np.empty(len(points), dtype=np.int64)
    for n in range(len(points)):
        order[start[keys[n]]] = n
        start[keys[n]] += 1
    return order


@njit(cache=True, parallel=True, nogil=True)
def _grid_distances(points, grid, cap2, ordered=False):
    """Exact distance from each point to the nearest triangle of the grid's mesh (see
    _nearest_sq for ``cap2``), searched in order of blocks of cells, or (``ordered``) in
    the points' own order when neighbours come together already."""
    lo, cell, dims, offsets, items, tri = grid
    n_points = len(points)
    order = np.arange(n_points) if ordered else _block_order(points, lo, cell, dims)
    lox, loy, loz, nx, ny, nz = lo[0], lo[1], lo[2], dims[0], dims[1], dims[2]
    found = np.empty(n_points)
    for n in prange(n_points):
        # written in search order: threads writing all over ``out`` would contend for its
        # cache lines (4x slower for 10 000 points)
        q = order[n]
        px, py, pz = points[q, 0], points[q, 1], points[q, 2]
        d2 = _nearest_sq(px, py, pz, lox, loy, loz, cell, nx, ny, nz, offsets, items, tri, cap2)
        found[n] = math.sqrt(d2)
    if ordered:
        return found
    out = np.empty(n_points)
    out[order] = found
    return out


def jit_grid(mesh: Mesh) -> tuple:
    """The cells of ``mesh``'s triangles that :func:`distances_to` searches, made by numba's
    kernels (:func:`miss.measure.surface_grid` picks these or the native ones, the same cells)."""
    # float32 vertices and int32 faces as they are (the kernels compute in float64): no copies
    verts = np.ascontiguousarray(mesh.vertices)
    faces = np.ascontiguousarray(mesh.faces)
    lo, cell, dims = _grid_shape(verts, faces)
    spans = np.empty((len(faces), 6), dtype=np.int16 if dims.max() < 2**15 else np.int32)
    tri = _corners(verts, faces, lo, cell, dims, spans)
    offsets, items = _build_grid(spans, dims)
    return (lo, cell, dims, offsets, items, tri)


def distances_to(
    points: np.ndarray,
    mesh: Mesh,
    cap: float = math.inf,
    grid: tuple | None = None,
    ordered: bool = False,
) -> np.ndarray:
    """Unsigned distance in mm from each of (P, 3) points to the surface of ``mesh``.

    Distances up to ``cap`` (mm) are exact; a larger one is only known to exceed it (a
    check against a bound needs no more, and a point far from every triangle, where a
    piece was lost, would otherwise search the whole grid). ``grid``: ``mesh``'s
    :func:`miss.measure.surface_grid`, when the caller keeps it. ``ordered``: the points come with their
    neighbours already (a mesh's vertices, edges or triangles in order), so they are
    searched as they come rather than sorted by cell first (same answers)."""
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    if mesh.n_triangles == 0:
        return np.full(len(pts), np.inf)
    grid = grid or jit_grid(mesh)
    return _grid_distances(pts, grid, cap * cap, ordered)


def side_of(a: Mesh, samples: int = 100_000, seed: int = 0) -> Side:
    """``a``'s :class:`Side` of a :func:`deviation` with ``samples`` and ``seed``."""
    return half(a, samples, seed, JITTED)


def deviation(
    a: Mesh, b: Mesh, samples: int = 100_000, seed: int = 0, side: Side | None = None
) -> Deviation:
    """Two-sided (symmetric Hausdorff-style) deviation between surfaces ``a`` and ``b``;
    ``side``: ``a``'s half made already (:func:`side_of`, the same ``samples`` and ``seed``).
    The same points as :func:`sample_surface`'s, neighbours together (max and mean are the
    same): see :func:`miss.measure._native.measure`."""
    return measure(a, b, samples, seed, side, JITTED)


#: numba's kernels, as :func:`miss.measure._native.measure` takes them.
JITTED = Kernels(
    sample=lambda mesh, count, rng: _sample(mesh, count, rng, drawn=False),
    grid=jit_grid,
    search=lambda points, grid, ordered: _grid_distances(points, grid, math.inf, ordered),
)


def between(before: Mesh, after: Mesh, samples: int, seed: int) -> float:
    """Max distance (mm) between the points :func:`bound_check` measures, found densely:
    every edge of ``after`` at each eighth of its length and ``samples`` random points
    inside its triangles to ``before``; every edge's midpoint of ``before`` and ``samples``
    random points inside its triangles to ``after`` (area-weighted, ``seed``). For tests
    and benchmarks that check a bound is held everywhere, not only where it is checked."""
    rng = np.random.default_rng(seed)
    v, e = after.vertices.astype(np.float64), _edge_list(after)
    steps = np.arange(1, 8) / 8.0
    along = v[e[:, 0], None, :] * (1.0 - steps)[:, None] + v[e[:, 1], None, :] * steps[:, None]
    back = distances_to(
        np.concatenate([along.reshape(-1, 3), sample_surface(after, samples, rng)]), before
    )
    w, g = before.vertices.astype(np.float64), _edge_list(before)
    there = distances_to(
        np.concatenate([0.5 * (w[g[:, 0]] + w[g[:, 1]]), sample_surface(before, samples, rng)]),
        after,
    )
    return max(float(back.max()), float(there.max()))


def _edge_list(mesh: Mesh) -> np.ndarray:
    """(E, 2) the edges of ``mesh``, each once: :func:`_unique_edges` against no input."""
    n = mesh.n_vertices
    none = np.empty((0, 3), dtype=np.int32), np.zeros(n + 1, np.int64), np.empty(0, np.int32)
    return _unique_edges(np.ascontiguousarray(mesh.faces), n, *none)


@njit(cache=True, nogil=True)
def nearest_face(p, verts, faces):
    """Index of the triangle of ``faces`` nearest to point p (brute force, boxes first):
    for a few points, without a grid."""
    px, py, pz = float(p[0]), float(p[1]), float(p[2])
    best, found = np.inf, -1
    for f in range(len(faces)):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        gap = 0.0
        for k, q in ((0, px), (1, py), (2, pz)):
            lo = min(verts[a, k], verts[b, k], verts[c, k])
            hi = max(verts[a, k], verts[b, k], verts[c, k])
            gap += _box_sq(q, lo, hi)
        if gap >= best:
            continue
        d = triangle_sq(
            px, py, pz, verts[a, 0], verts[a, 1], verts[a, 2], verts[b, 0], verts[b, 1],
            verts[b, 2], verts[c, 0], verts[c, 1], verts[c, 2],
        )  # fmt: skip
        if d < best:
            best, found = d, f
    return found


@dataclass(frozen=True)
class BoundCheck:
    """The deviation of a decimation whose vertices are a subset of its input's, both ways.

    ``to_output`` (N,): each input vertex's distance to the output surface (0 for the
    vertices the output kept; NaN for vertices no input triangle uses). ``edges`` (E, 2) and
    ``edge_mm`` (E,): the output's edges and their midpoints' distance to the input surface;
    ``faces`` (G, 3) and ``face_mm`` (G,): the output's new triangles (not the input's) and
    their centroids' distance to it (none when the check left centroids out); ``edges``
    are the new triangles' edges that are not the input's. All mm.
    """

    max_mm: float
    mean_mm: float
    samples: int
    to_output: np.ndarray
    edges: np.ndarray
    edge_mm: np.ndarray
    faces: np.ndarray
    face_mm: np.ndarray


@njit(cache=True, inline="always")
def _has_corner(faces, f, v):
    return faces[f, 0] == v or faces[f, 1] == v or faces[f, 2] == v


@njit(cache=True, inline="always")
def _input_edge(before, start, items, a, b):
    """Whether ab is an edge of ``before``: on its surface already."""
    for i in range(start[a], start[a + 1]):  # noqa: SIM110 (numba: no any() of a generator)
        if _has_corner(before, items[i], b):
            return True
    return False


@njit(cache=True, nogil=True)
def _unique_edges(faces, n_vertices, before, start_in, items_in):
    """(E, 2) int64: the edges of ``faces`` (F, 3) that are not edges of ``before`` (its
    triangles around each vertex: ``start_in``, ``items_in``), each once, smaller vertex
    first, in order of that vertex (the larger ones of a vertex in the order met). Bucketed
    by the smaller vertex, each bucket a few: linear, where sorting 3 F keys took 4x
    longer."""
    start = np.zeros(n_vertices + 1, dtype=np.int64)
    for f in range(len(faces)):
        for k in range(3):
            a, b = faces[f, k], faces[f, (k + 1) % 3]
            start[min(a, b) + 1] += 1
    for v in range(n_vertices):
        start[v + 1] += start[v]
    other = np.empty(start[n_vertices], dtype=np.int64)
    fill = start[:-1].copy()
    for f in range(len(faces)):
        for k in range(3):
            a, b = faces[f, k], faces[f, (k + 1) % 3]
            lo = min(a, b)
            other[fill[lo]] = max(a, b)
            fill[lo] += 1
    out = np.empty((len(other), 2), dtype=np.int64)
    n = 0
    for v in range(n_vertices):
        for i in range(start[v], start[v + 1]):
            seen = False
            for j in range(start[v], i):
                if other[j] == other[i]:
                    seen = True
                    break
            if not seen and not _input_edge(before, start_in, items_in, v, other[i]):
                out[n, 0], out[n, 1] = v, other[i]
                n += 1
    return out[:n]


@njit(cache=True, nogil=True)
def _adjacency(faces, n_vertices):
    """(start, items): the triangles around each vertex, CSR (vertex v's are
    items[start[v]:start[v + 1]])."""
    start = np.zeros(n_vertices + 1, dtype=np.int64)
    for f in range(len(faces)):
        for k in range(3):
            start[faces[f, k] + 1] += 1
    for v in range(n_vertices):
        start[v + 1] += start[v]
    items = np.empty(start[n_vertices], dtype=np.int32)
    fill = start[:-1].copy()
    for f in range(len(faces)):
        for k in range(3):
            items[fill[faces[f, k]]] = f
            fill[faces[f, k]] += 1
    return start, items


def surface_adjacency(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """The triangles around each vertex of ``mesh`` (see :func:`bound_check`): made once
    for several checks against one input."""
    return _adjacency(np.ascontiguousarray(mesh.faces), mesh.n_vertices)


@njit(cache=True, nogil=True)
def _new_faces(before, start, items, faces):
    """The rows of ``faces`` that are not triangles of ``before`` (whatever their corners'
    order; looked for among the input triangles around their first corner), in order."""
    new = np.empty(len(faces), dtype=np.bool_)
    n = 0
    for g in range(len(faces)):
        a, b, c = faces[g, 0], faces[g, 1], faces[g, 2]
        new[g] = True
        for i in range(start[a], start[a + 1]):
            f = items[i]
            if _has_corner(before, f, b) and _has_corner(before, f, c):
                new[g] = False
                break
        n += new[g]
    out = np.empty((n, 3), dtype=faces.dtype)
    n = 0
    for g in range(len(faces)):
        if new[g]:
            out[n] = faces[g]
            n += 1
    return out


@njit(cache=True, nogil=True)
def _check_points(verts, dropped, edges, faces):
    """The ``dropped`` vertices, then the midpoints of ``edges``, then the centroids of
    ``faces``, float64: what bound_check measures (one array, no copies between)."""
    out = np.empty((len(dropped) + len(edges) + len(faces), 3))
    for n in range(len(dropped)):
        for k in range(3):
            out[n, k] = verts[dropped[n], k]
    at = len(dropped)
    for e in range(len(edges)):
        for k in range(3):
            out[at + e, k] = 0.5 * (float(verts[edges[e, 0], k]) + float(verts[edges[e, 1], k]))
    at += len(edges)
    for f in range(len(faces)):
        for k in range(3):
            total = float(verts[faces[f, 0], k]) + float(verts[faces[f, 1], k])
            out[at + f, k] = (total + float(verts[faces[f, 2], k])) / 3.0
    return out


@njit(cache=True, nogil=True)
def dropped_vertices(before_faces, after_faces, n_vertices):
    """(used, dropped): the vertices some input triangle uses (bool) and, in increasing
    order, those of them no output triangle does."""
    used = _used(before_faces, n_vertices)
    kept = _used(after_faces, n_vertices)
    n = 0
    for v in range(n_vertices):
        if used[v] and not kept[v]:
            n += 1
    out = np.empty(n, dtype=np.int64)
    n = 0
    for v in range(n_vertices):
        if used[v] and not kept[v]:
            out[n] = v
            n += 1
    return used, out


def bound_check(
    before: Mesh,
    faces: np.ndarray,
    cap: float = math.inf,
    grid: tuple | None = None,
    adjacency: tuple[np.ndarray, np.ndarray] | None = None,
    centroids: bool = True,
    vertices: np.ndarray | None = None,
) -> BoundCheck:
    """Two-sided deviation (mm) of the output ``faces`` (M, 3), which index ``before``'s
    vertices (or ``vertices``, see below), from ``before``'s surface: every input vertex
    the output dropped to the output surface, and the output's edge midpoints and triangle
    centroids to the input surface.

    The output's own vertices are input vertices (distance 0), so this covers every vertex
    both ways exactly, plus the points where a new triangle bulges from the input most
    (its edges' and interior's middles), not random samples. Distances above ``cap`` (mm)
    are only known to exceed it (see :func:`distances_to`). A triangle or an edge the input
    has too lies on it: only the new triangles and their new edges are measured (found
    among the input's triangles around their corners). ``grid`` (``before``'s
    :func:`miss.measure.surface_grid`) and ``adjacency`` (its :func:`surface_adjacency`): kept by a
    caller that checks several outputs of one input.

    ``centroids`` False leaves the new triangles' centroids out (``faces`` and ``face_mm``
    empty), for an output whose bound holds by construction (schroeder's: see
    :func:`miss.decimate._fan.overlay_gap`), where the check measures what the contract
    names, every input vertex and every output vertex and edge midpoint, and not a point
    more: on the 15 surfaces and bounds of ``benchmarks/bounds.py`` no centroid was ever the
    farthest point (the largest was an input vertex at 13, an edge midpoint at 2), and they
    were 28-47 % of the points searched.

    ``vertices`` (N, 3), for an output that moved some of ``before``'s vertices (the placed
    collapse, :mod:`miss.decimate.placed`): the faces index it. An output vertex that moved
    is measured to the input (as an edge from it to itself in ``edges``), every input vertex
    it moved from to the output, and every output triangle or edge with a moved corner is
    new.
    """
    if vertices is not None:
        moved = (np.asarray(vertices) != before.vertices).any(axis=1)
        kept = np.zeros(len(moved), dtype=bool)
        kept[np.asarray(faces).ravel()] = True
        moved &= kept  # (a vertex no output triangle uses is not on the output)
        if moved.any():
            return _moved_check(before, faces, vertices, moved, cap, grid, adjacency, centroids)
    faces = np.ascontiguousarray(faces)
    used_in, dropped = dropped_vertices(
        np.ascontiguousarray(before.faces), faces, before.n_vertices
    )
    to_output = np.where(used_in, 0.0, np.nan)
    after = Mesh(vertices=before.vertices, faces=faces)
    with ThreadPoolExecutor(max_workers=1) as pool:
        # the output's cells are made on the second core while this one finds what is new
        # (both serial; 35 ms of CThead bone's check were)
        making = pool.submit(jit_grid, after) if len(dropped) and len(faces) else None
        start, items = adjacency or surface_adjacency(before)
        inputs = np.ascontiguousarray(before.faces)
        new = _new_faces(inputs, start, items, faces)
        edges = _unique_edges(new, before.n_vertices, inputs, start, items)
        if not centroids:
            new = new[:0]
        verts = np.ascontiguousarray(before.vertices)
        points = _check_points(verts, dropped, edges, new)
        # in vertex, edge and triangle order: neighbours together already, no block sort
        of_input, of_output = points[: len(dropped)], points[len(dropped) :]
        back = np.zeros(0)
        if len(of_output):
            back = distances_to(of_output, before, cap, grid, ordered=True)
        if len(dropped):
            out_grid = making.result() if making is not None else None
            to_output[dropped] = distances_to(of_input, after, cap, out_grid, ordered=True)
    return _summed(to_output, dropped, used_in, back, edges, new)


def _summed(
    to_output: np.ndarray,
    measured: np.ndarray,
    used_in: np.ndarray,
    back: np.ndarray,
    edges: np.ndarray,
    new: np.ndarray,
) -> BoundCheck:
    """A check's figures: ``to_output`` (N,) measured at the input vertices ``measured``
    (the rest used 0), ``back``: the midpoints of ``edges`` then the centroids of ``new``
    to the input."""
    edge_mm, face_mm = back[: len(edges)], back[len(edges) :]
    # the mean over every input vertex (kept ones at 0) and every output point measured
    total = float(to_output[measured].sum()) + float(back.sum())
    count = int(used_in.sum()) + len(back)
    top = max(
        float(to_output[measured].max()) if len(measured) else 0.0,
        float(back.max()) if len(back) else 0.0,
    )
    return BoundCheck(
        max_mm=top,
        mean_mm=total / count if count else 0.0,
        samples=count,
        to_output=to_output,
        edges=edges,
        edge_mm=edge_mm,
        faces=new,
        face_mm=face_mm,
    )


def _moved_check(
    before: Mesh,
    faces: np.ndarray,
    vertices: np.ndarray,
    moved: np.ndarray,
    cap: float,
    grid: tuple | None,
    adjacency: tuple[np.ndarray, np.ndarray] | None,
    centroids: bool,
) -> BoundCheck:
    """:func:`bound_check` of an output whose ``moved`` (N,) vertices are not where the
    input has them (``vertices``: where the output has every one)."""
    faces = np.ascontiguousarray(faces)
    n = before.n_vertices
    used_in, dropped = dropped_vertices(np.ascontiguousarray(before.faces), faces, n)
    # the input vertices the output no longer has where they were
    left = moved & used_in
    left[dropped] = True
    away = np.flatnonzero(left)  # (np.union1d hashes: seconds on the MR head's 4 M)
    verts = np.ascontiguousarray(vertices)  # in their own type, as the kernels take the input's
    after = Mesh(vertices=verts, faces=faces)
    start, items = adjacency or surface_adjacency(before)
    inputs = np.ascontiguousarray(before.faces)
    touched = moved[faces].any(axis=1)
    new = _new_faces(inputs, start, items, faces[~touched])
    new = np.concatenate([new, faces[touched]])
    edges = _unique_edges(new, n, inputs, start, items)
    # an input edge with a moved end is new too; a moved vertex, as an edge to itself
    rows = faces[touched]
    pairs = np.concatenate([rows[:, [k, (k + 1) % 3]] for k in range(3)]).astype(np.int64)
    pairs = pairs[moved[pairs].any(axis=1)]
    pairs.sort(axis=1)
    itself = np.repeat(np.flatnonzero(moved), 2).reshape(-1, 2).astype(np.int64)
    every = np.concatenate([edges, pairs, itself])
    keys = np.sort(every[:, 0] * n + every[:, 1])
    keys = keys[np.concatenate([[True], keys[1:] != keys[:-1]])]  # each once, in order
    edges = np.stack([keys // n, keys % n], axis=1)
    if not centroids:
        new = new[:0]
    of_input = np.asarray(before.vertices, dtype=np.float64)[away]
    wide = verts.astype(np.float64)
    of_output = np.concatenate(
        [0.5 * (wide[edges[:, 0]] + wide[edges[:, 1]]), wide[new].mean(axis=1)]
    )
    # both in vertex order: neighbours together already
    back = (
        distances_to(of_output, before, cap, grid, ordered=True) if len(of_output) else np.zeros(0)
    )
    to_output = np.where(used_in, 0.0, np.nan)
    if len(away):
        to_output[away] = distances_to(of_input, after, cap, ordered=True)
    return _summed(to_output, away, used_in, back, edges, new)
