"""Blockwise isosurfaces: flying edges per 3-D block, welded exactly on the shared faces.

The region (sampled, padded one voxel below the level all round, as in
:func:`miss.surface.extract_surface`) is cut into boxes of cells. A block reads only its
own points from the source array (``numpy.ndarray`` or ``zarr.Array``: box slicing, with
the sample step as the slice step), so a volume on disk is never read whole.

Exactness: every vertex lies on one grid edge. VTK interpolates the three voxel indices
as float64 point data, which names that edge (two whole-number coordinates and the lower
end of the third), and the position is recomputed as ``edge start + t`` with
``t = (level - s0) / (s1 - s0)`` in float64 from the two voxel values. That number does
not depend on where the block starts, so every block size gives the same vertices, bit
for bit, and vertices on a shared face are welded by their edge's id (an exact integer).
Triangles belong to cells, and each cell to one block, so the triangles are those of one
flying-edges run over the whole padded region (tested against it).
"""

from __future__ import annotations

import itertools
import mmap
import threading
from collections import OrderedDict
from collections.abc import Callable
from contextlib import suppress
from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import numpy as np
from vtkmodules.util import numpy_support
from vtkmodules.vtkFiltersCore import vtkFlyingEdges3D

from miss._vtk import image_data
from miss.surface import _use_both_cores

Box = tuple[tuple[int, int], ...]  # per axis (first point, last point), padded grid, inclusive
#: Changes a block's points (F-ordered, read over the box) before they are contoured.
Edit = Callable[[np.ndarray, Box], np.ndarray]


@dataclass(frozen=True)
class Grid:
    """What a block task needs to read and contour its box; small and picklable.

    ``data`` travels by reference when it is a ``zarr.Array`` (its store path).
    ``start``/``step`` say where the region's sampled voxel ``s`` sits in ``data``
    (``start + s * step``); ``shape`` is the sampled region's voxel count. Padded point
    ``p`` (0 .. shape + 1) is region voxel ``p - 1``; 0 and shape + 1 hold ``pad``.
    """

    data: Any
    start: tuple[int, int, int]
    step: tuple[int, int, int]
    shape: tuple[int, int, int]
    pad: float
    dtype: str

    @property
    def padded(self) -> tuple[int, int, int]:
        """The shape with one pad voxel on each side of every axis."""
        x, y, z = self.shape
        return x + 2, y + 2, z + 2


@dataclass(frozen=True)
class BlockMesh:
    """One block's triangles: vertices (N, 3) float64 in padded index space, faces (F, 3)
    int32 into them, normals (N, 3) float32 or (N, 0), and the edge ids (int64) of the
    vertices on the block's faces (``shared``: their local indices)."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    shared: np.ndarray
    keys: np.ndarray
    #: the smallest and largest region voxel the block read (its pad aside)
    span: tuple[float, float] = (np.inf, -np.inf)
    #: what decimating it where it was made did (``miss.surface.blockwise.blockwise_decimated``)
    decimated: Decimated | None = None
    #: the block it is (its cells in the padded grid), for a weld in the blocks' order
    box: Box | None = None


@dataclass(frozen=True)
class Decimated:
    """A block decimated where it was made: its measured maximum and mean deviation from
    its full-resolution surface (mm), its triangles before, and that surface's extent
    (lowest and highest x, y, z, mm)."""

    max_mm: float
    mean_mm: float
    triangles_in: int
    lo: np.ndarray
    hi: np.ndarray


def cell_blocks(padded: tuple[int, int, int], edge: tuple[int, int, int]) -> list[Box]:
    """Boxes of about ``edge`` cells per axis covering the padded grid's cells; neighbours
    share their face points."""
    ranges = []
    for n, e in zip(padded, edge, strict=True):
        cuts = list(range(0, n - 1, max(1, e))) + [n - 1]
        ranges.append([(a, b) for a, b in itertools.pairwise(cuts)])
    return [tuple(box) for box in itertools.product(*ranges)]


def read_points(grid: Grid, box: Box) -> np.ndarray:
    """The padded grid's points in ``box`` (F-ordered), the pad where it leaves the region."""
    out = np.full([b - a + 1 for a, b in box], grid.pad, dtype=grid.dtype, order="F")
    src, dst = [], []
    for (a, b), n, st, s0 in zip(box, grid.shape, grid.step, grid.start, strict=True):
        lo, hi = max(a, 1), min(b, n)  # padded points that are region voxels
        if lo > hi:
            return out
        src.append(slice(s0 + (lo - 1) * st, s0 + (hi - 1) * st + 1, st))
        dst.append(slice(lo - a, hi - a + 1))
    out[tuple(dst)] = read_box(grid.data, tuple(src))
    return out


class ChunkCache:
    """Decompressed chunks of arrays on disk, the most recently used kept up to ``limit``
    bytes; shared by the threads of a process (each Dask worker has its own). Kept
    chunks are read-only: readers copy out of them.

    Neighbouring blocks share a plane of points, and a block's box rarely ends on a chunk
    boundary, so without it a chunk on a seam is decompressed once for every block that
    touches it (up to 8 times, 3.4x the work for blocks of two chunks a side). A server
    keeps one of its own for slices (``Store.chunks``): a slice crosses a layer of chunks
    of 64 planes each, so scrubbing viewers read the same chunks over and over."""

    def __init__(self, limit: int) -> None:
        self.limit, self.held = limit, 0
        self.chunks: OrderedDict[tuple[Any, ...], np.ndarray] = OrderedDict()
        self.lock = threading.Lock()

    def get(self, key: tuple[Any, ...], load: Callable[[], np.ndarray]) -> np.ndarray:
        """The chunk at ``key``, read by ``load`` when not held; the least recently used
        dropped past the limit."""
        with self.lock:
            if key in self.chunks:
                self.chunks.move_to_end(key)
                return self.chunks[key]
        chunk = load()  # outside the lock: two threads may read one chunk, never wait
        chunk.flags.writeable = False  # shared by every reader from now on
        with self.lock:
            if key not in self.chunks:
                self.chunks[key] = chunk
                self.held += chunk.nbytes
            while self.held > self.limit and len(self.chunks) > 1:
                _, dropped = self.chunks.popitem(last=False)
                self.held -= dropped.nbytes
        return chunk

    def drop(self, test: Callable[[tuple[Any, ...]], bool]) -> None:
        """Forget the chunks whose key passes ``test`` (an array deleted)."""
        with self.lock:
            for key in [k for k in self.chunks if test(k)]:
                self.held -= self.chunks.pop(key).nbytes


#: This process's chunk cache: 256 MB, a layer of 64-voxel chunks of a 1000 x 2000 grid.
CHUNKS = ChunkCache(256 << 20)


def done_with(data: Any) -> None:
    """Forget the chunks of ``data`` (an array on disk) this process keeps, and hand the
    memory freed back to the system: once a surface's blocks are made, what follows (the
    decimation across them) needs it more. glibc keeps freed blocks' memory for reuse
    (the 1.18 GB volume of ``benchmarks/big_volume.py`` held 350 MB more at its peak
    without this), so ``malloc_trim`` returns it; elsewhere only the chunks go."""
    name = _array_name(data)
    if name is not None:
        CHUNKS.drop(lambda key: key[0] == name)
    with suppress(OSError, AttributeError):  # not glibc: nothing to trim
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)


def read_box(data: Any, src: tuple[slice, ...]) -> np.ndarray:
    """``data[src]`` as numpy; an array on disk with ``chunks`` (unit steps) is read a
    whole chunk at a time through :data:`CHUNKS`."""
    chunks, name = getattr(data, "chunks", None), _array_name(data)
    if chunks is None or name is None or any(sl.step not in (None, 1) for sl in src):
        return np.asarray(data[src])
    bounds = [(sl.start, sl.stop) for sl in src]
    out = np.empty([b - a for a, b in bounds], dtype=data.dtype, order="F")
    spans = [range(a // c, (b - 1) // c + 1) for (a, b), c in zip(bounds, chunks, strict=True)]
    for index in itertools.product(*spans):
        lo = [i * c for i, c in zip(index, chunks, strict=True)]
        box = tuple(slice(a, min(a + c, n)) for a, c, n in zip(lo, chunks, data.shape, strict=True))
        chunk = CHUNKS.get((name, *index), partial(_load_chunk, data, index, box))
        overlap = [
            (max(a, c0), min(b, c0 + c)) for (a, b), c0, c in zip(bounds, lo, chunks, strict=True)
        ]
        take = tuple(slice(a - c0, b - c0) for (a, b), c0 in zip(overlap, lo, strict=True))
        put = tuple(slice(a - s0, b - s0) for (a, b), (s0, _) in zip(overlap, bounds, strict=True))
        out[put] = chunk[take]
    return out


def _load_chunk(data: Any, index: tuple[int, ...], box: tuple[slice, ...]) -> np.ndarray:
    """Chunk ``index`` of ``data`` (``box``: its voxels): straight from its file when the
    array offers ``chunk`` (:class:`miss.server.storage.chunked.Voxels`), else sliced."""
    read = getattr(data, "chunk", None)
    return read(index) if read is not None else np.asarray(data[box])


def _array_name(data: Any) -> str | None:
    """Where an array on disk lives (the same after pickling to a worker), else None."""
    stored = getattr(data, "stored", data)  # miss.server.storage.chunked.Voxels
    where = getattr(stored, "store_path", None)
    return None if where is None else f"{where}:{getattr(data, 'shape', '')}"


def voxel_boxes(grid: Grid, edge: int) -> list[Box]:
    """Boxes of region voxels (inclusive, no overlap) for the min/max pass: ``edge``
    voxels, or whole chunks of ``grid.data`` (its ``chunks``, at unit steps) that many
    voxels wide, so that no chunk is decompressed twice."""
    chunks = getattr(grid.data, "chunks", None)
    ranges = []
    for k, (n, st, s0) in enumerate(zip(grid.shape, grid.step, grid.start, strict=True)):
        size = edge
        if chunks is not None and st == 1:
            size = max(1, edge // chunks[k]) * chunks[k]
            first = (s0 // chunks[k] + 1) * chunks[k] - s0  # the first chunk boundary
            cuts = [0, *range(first % size or size, n, size), n]
        else:
            cuts = [*range(0, n, size), n]
        ranges.append([(a, b - 1) for a, b in itertools.pairwise(sorted(set(cuts))) if b > a])
    return [tuple(box) for box in itertools.product(*ranges)]


def block_range(grid: Grid, box: Box) -> tuple[float, float]:
    """Minimum and maximum of the region's voxels in ``box`` (region voxel indices)."""
    src = tuple(
        slice(s0 + a * st, s0 + b * st + 1, st)
        for (a, b), st, s0 in zip(box, grid.step, grid.start, strict=True)
    )
    part = read_box(grid.data, src)
    return float(part.min()), float(part.max())


def surface_block(
    grid: Grid, box: Box, level: float, normals: bool, edit: Edit | None = None
) -> BlockMesh:
    """Flying edges over one box's cells; vertices placed exactly (see the module's note).

    With ``normals`` the box is read with one context point beyond each inner face, so the
    gradients on the face are central differences as in one run over the whole region; the
    context cells' triangles (a vertex beyond the face) are dropped. ``edit(points, read)``
    may change the points read (over the box ``read``) before they are contoured: the
    blockwise components blank the pieces not chosen.
    """
    context = 1 if normals else 0
    read = tuple(
        (max(a - context, 0), min(b + context, n - 1))
        for (a, b), n in zip(box, grid.padded, strict=True)
    )
    points = read_points(grid, read)
    if edit is not None:
        points = edit(points, read)
    span = _region_span(points, read, grid.shape)
    if not points.min() < level <= points.max():  # all inside or all outside: no triangle
        return replace(_empty_block(normals), span=span)
    origin = np.array([r[0] for r in read], dtype=np.int64)
    local, faces, vectors = _contour_with_indices(points, level, normals)
    if len(faces) == 0:
        return replace(_empty_block(normals), span=span)
    axis, base, verts = _exact_positions(points, local, level)
    if context:
        lo = np.array([a for a, _ in box], dtype=np.float64) - origin
        hi = np.array([b for _, b in box], dtype=np.float64) - origin
        beyond = np.any((verts < lo) | (verts > hi), axis=1)  # an array to numpy's stubs
        faces = faces[~(beyond[faces].any(axis=1))]
        used = np.zeros(len(verts), dtype=bool)
        used[faces.ravel()] = True
        renumber = np.cumsum(used) - 1
        faces = renumber[faces].astype(np.int32)
        axis, base, verts, vectors = axis[used], base[used], verts[used], vectors[used]
    base += origin
    verts += origin
    shared = _on_block_faces(base, axis, box)
    keys = _edge_keys(base[shared], axis[shared], grid.padded)
    return BlockMesh(verts, faces, vectors, shared, keys, span)


def _region_span(points: np.ndarray, read: Box, shape: tuple[int, int, int]) -> tuple[float, float]:
    """Minimum and maximum of the region voxels among ``points`` (read over ``read``)."""
    inner = tuple(
        slice(max(a, 1) - a, min(b, n) - a + 1) for (a, b), n in zip(read, shape, strict=True)
    )
    voxels = points[inner]
    if voxels.size == 0:
        return np.inf, -np.inf
    return float(voxels.min()), float(voxels.max())


def _empty_block(normals: bool) -> BlockMesh:
    return BlockMesh(
        np.zeros((0, 3)),
        np.zeros((0, 3), np.int32),
        np.zeros((0, 3 if normals else 0), np.float32),
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
    )


def _contour_with_indices(
    points: np.ndarray, level: float, normals: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flying edges with the voxel indices interpolated as float64 point data.

    Returns the interpolated indices (N, 3) float64, faces (F, 3) int32, normals (N, 3)
    float32 or (N, 0).
    """
    _use_both_cores()
    image = image_data(points)
    keep = _index_arrays(points.shape)  # numpy_to_vtk(deep=False) does not own the memory
    for name, flat in zip("ijk", keep, strict=True):
        array = numpy_support.numpy_to_vtk(flat, deep=False)
        array.SetName(name)
        image.GetPointData().AddArray(array)
    fe = vtkFlyingEdges3D()
    fe.SetInputData(image)
    fe.SetValue(0, float(level))
    fe.SetComputeNormals(normals)
    fe.ComputeGradientsOff()
    fe.ComputeScalarsOff()
    fe.InterpolateAttributesOn()
    fe.Update()
    del keep  # VTK's output holds copies
    out = fe.GetOutput()
    if out.GetNumberOfPoints() == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros((0, 0), np.float32)
    data = out.GetPointData()
    local = np.stack([numpy_support.vtk_to_numpy(data.GetArray(n)) for n in "ijk"], axis=1)
    conn = numpy_support.vtk_to_numpy(out.GetPolys().GetConnectivityArray())
    faces = conn.astype(np.int32).reshape(-1, 3)
    if normals:
        vectors = numpy_support.vtk_to_numpy(data.GetNormals()).astype(np.float32)
    else:
        vectors = np.zeros((len(local), 0), np.float32)
    return local.astype(np.float64, copy=False), faces, vectors


#: The index arrays of recent block shapes (read-only; most blocks share one shape):
#: building them took a sixth of a block's time. At most ``_INDEX_BYTES`` kept.
_INDEX_ARRAYS: OrderedDict[tuple[int, ...], tuple[np.ndarray, ...]] = OrderedDict()
_INDEX_BYTES = 160 << 20
_INDEX_LOCK = threading.Lock()


def _index_arrays(shape: tuple[int, ...]) -> tuple[np.ndarray, ...]:
    """Each point's i, j and k as three flat float64 arrays (F order) for a grid of
    ``shape``, shared by the blocks of that shape."""
    with _INDEX_LOCK:
        if shape in _INDEX_ARRAYS:
            _INDEX_ARRAYS.move_to_end(shape)
            return _INDEX_ARRAYS[shape]
    arrays = []
    for k in range(3):
        along = [1, 1, 1]
        along[k] = shape[k]
        index = np.empty(shape, dtype=np.float64, order="F")
        index[...] = np.arange(shape[k], dtype=np.float64).reshape(along)
        flat = index.ravel(order="F")  # a view: F-ordered
        flat.flags.writeable = False
        arrays.append(flat)
    made = tuple(arrays)
    with _INDEX_LOCK:
        _INDEX_ARRAYS[shape] = made
        while (
            len(_INDEX_ARRAYS) > 1
            and sum(a.nbytes for v in _INDEX_ARRAYS.values() for a in v) > _INDEX_BYTES
        ):
            _INDEX_ARRAYS.popitem(last=False)
    return made


def _exact_positions(
    points: np.ndarray, local: np.ndarray, level: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(edge axis (N,) int8, edge start (N, 3) int64, position (N, 3) float64) of each
    vertex, the position ``start + t`` with t from the edge's two voxel values.

    A vertex that VTK's float64 indices put exactly on a voxel (float data within ~1e-13
    of the level: t rounds to 0 or 1) keeps that voxel as its position and gets axis 3;
    two such vertices at one voxel on a block face are welded into one (a difference from
    the single pass only there).
    """
    floor = np.floor(local)
    off_grid = local != floor
    moving = off_grid.any(axis=1)
    axis = np.argmax(off_grid, axis=1).astype(np.int8)
    axis[~moving] = 3
    base = floor.astype(np.int64)
    verts = floor
    rows = np.flatnonzero(moving)
    a = axis[rows]
    # the edge's two voxel values through the flat (F-ordered) points: one gather each
    strides = np.array([1, points.shape[0], points.shape[0] * points.shape[1]], np.int64)
    start = base[rows] @ strides
    flat = points.ravel(order="F")
    s0 = flat[start].astype(np.float64)
    s1 = flat[start + strides[a]].astype(np.float64)
    verts[rows, a] += (level - s0) / (s1 - s0)
    return axis, base, verts


def _on_block_faces(base: np.ndarray, axis: np.ndarray, box: Box) -> np.ndarray:
    """Local indices of the vertices whose edge lies in one of the box's face planes."""
    on = np.zeros(len(base), dtype=bool)
    for k, (a, b) in enumerate(box):
        across = axis != k  # an edge along k never lies in a plane normal to k
        on |= across & ((base[:, k] == a) | (base[:, k] == b))
    return np.flatnonzero(on)


def _edge_keys(base: np.ndarray, axis: np.ndarray, padded: tuple[int, int, int]) -> np.ndarray:
    """One integer per grid edge: (linear index of its start point) * 4 + axis (3 for a
    vertex on the voxel itself)."""
    nx, ny, _ = padded
    linear = (base[:, 2] * ny + base[:, 1]) * nx + base[:, 0]
    return linear * 4 + axis.astype(np.int64)


class Welder:
    """Welds block meshes as they arrive (one vertex per edge id on the blocks' faces);
    ``result()`` returns the welded mesh.

    Each block is numbered and written into the output when it comes: its vertices in
    their order, less those whose edge id an earlier block (or an earlier vertex of its
    own) had, which take that vertex's number. So the work is done while the other
    blocks are being made, and what is left when the last one arrives is that block's
    own. The result equals a weld of all blocks at the end in arrival order (vertex for
    vertex); a weld left to the end keeps the workers waiting for it. Blocks made on
    threads of this process wait for :meth:`result` (``as_they_come=False``): there the
    weld would hold the interpreter while they run, and it is no faster.

    ``in_order``: :meth:`result` renumbers the mesh welded in arrival order to the one a
    weld in the blocks' order makes (the order each block was given to :meth:`add`), for
    a mesh decimated next, whose decimation depends on the numbering: a job on a cluster
    then makes the model it makes on threads, every run. It costs a sort of the vertices'
    places and a copy of the mesh, so the surface alone is left in arrival order."""

    def __init__(self, as_they_come: bool = True, in_order: bool = False) -> None:
        #: False: blocks are kept as they come and welded in :meth:`result` (the same
        #: mesh), for blocks made on threads of this process, which the weld would slow
        self.as_they_come = as_they_come
        #: True (with ``as_they_come``): :meth:`result` gives the mesh a weld in the blocks'
        #: order would have made (each block's ``order`` given to :meth:`add`), whatever
        #: order they came in, vertex for vertex and triangle for triangle
        self.in_order = in_order and as_they_come
        self.waiting: list[tuple[BlockMesh, np.ndarray, np.ndarray, int]] = []
        self.ids: dict[int, int] = {}  # edge id -> welded vertex number
        self.verts: _Rows | None = None
        self.normals: _Rows | None = None
        self.faces = _Rows(3, np.dtype(np.int32))
        # in_order: each welded vertex's place in that weld (block order, then its index in
        # the block that would have had it first), and each block's run of triangles
        self.places = _Rows(1, np.dtype(np.int64))
        self.runs: list[tuple[int, int, int]] = []  # (order, first triangle, triangles)

    def add(
        self, block: BlockMesh, vertices: np.ndarray, normals: np.ndarray, order: int = 0
    ) -> None:
        """Weld in a block whose vertices were mapped already (e.g. to mm, float32);
        ``order``: its place among the blocks (see ``in_order``)."""
        if not self.as_they_come:
            self.waiting.append((block, vertices, normals, order))
            return
        self._weld(block, vertices, normals, order)

    def _weld(
        self, block: BlockMesh, vertices: np.ndarray, normals: np.ndarray, order: int
    ) -> None:
        if self.verts is None:
            self.verts = _Rows(vertices.shape[1], vertices.dtype)
            self.normals = _Rows(normals.shape[1], normals.dtype)
        assert self.normals is not None
        shared = block.shared
        # each edge id once, its first vertex in the block, and which one each vertex has
        keys, first, which = np.unique(block.keys, return_index=True, return_inverse=True)
        earlier = np.fromiter(  # an earlier block's number for it, or -1
            map(self.ids.get, keys.tolist(), itertools.repeat(-1)), np.int64, len(keys)
        )
        copy = (earlier[which] >= 0) | (first[which] != np.arange(len(which)))
        keep = np.ones(len(vertices), dtype=bool)
        keep[shared[copy]] = False
        kept = np.flatnonzero(keep)
        number_of = np.empty(len(vertices), dtype=np.int32)
        base = len(self.verts)
        number_of[kept] = np.arange(base, base + len(kept), dtype=np.int32)
        number = np.where(earlier >= 0, earlier, number_of[shared[first]])  # each edge id's
        number_of[shared] = number[which]
        new = earlier < 0
        self.ids.update(zip(keys[new].tolist(), number[new].tolist(), strict=True))
        if self.in_order:
            self.runs.append((order, len(self.faces), len(block.faces)))
            self._place(order, kept, earlier, shared[first], vertices, normals)
        for rows, of in ((self.verts, vertices), (self.normals, normals)):
            rows.extend(len(kept), partial(_take_rows, of, kept))
        self.faces.extend(
            len(block.faces), lambda out: np.take(number_of, block.faces, out=out, mode="clip")
        )

    def _place(
        self,
        order: int,
        kept: np.ndarray,
        earlier: np.ndarray,
        firsts: np.ndarray,
        vertices: np.ndarray,
        normals: np.ndarray,
    ) -> None:
        """Note where this block's vertices would be in a weld in the blocks' order: its
        own new ones, and the shared ones an earlier-come but later-placed block has
        (which take this block's place, and its vertex and normal, as that weld would)."""
        assert self.verts is not None and self.normals is not None
        top = np.int64(order) << 32
        self.places.extend(len(kept), lambda out: np.add(kept[:, None], top, out=out))
        had = np.flatnonzero(earlier >= 0)
        if len(had) == 0:
            return
        numbers, local = earlier[had], firsts[had]
        sooner = local + top < self.places.take(numbers)[:, 0]
        numbers, local = numbers[sooner], local[sooner]
        self.places.put(numbers, (local + top)[:, None])
        for rows, of in ((self.verts, vertices), (self.normals, normals)):
            rows.put(numbers, of[local])

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """vertices (N, 3), faces (F, 3) int32, normals of the welded mesh."""
        for waiting in self.waiting:
            self._weld(*waiting)
        self.waiting.clear()
        if self.verts is None or self.normals is None:
            return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32), np.zeros((0, 3))
        verts, faces, normals = self.verts.rows(), self.faces.rows(), self.normals.rows()
        if not self.in_order:
            return verts, faces, normals
        # the vertices in their places, the blocks' triangles in the blocks' order
        move = np.argsort(self.places.rows()[:, 0], kind="stable")
        runs = sorted(self.runs)
        if np.array_equal(move, np.arange(len(move))) and runs == self.runs:
            return verts, faces, normals  # they came in order
        number = np.empty(len(move), dtype=np.int32)
        number[move] = np.arange(len(move), dtype=np.int32)
        faces = np.concatenate([faces[first : first + n] for _, first, n in runs] or [faces])
        return verts[move], number[faces], normals[move]


def _take_rows(source: np.ndarray, rows: np.ndarray, out: np.ndarray) -> None:
    """``source[rows]`` written into ``out``, with no copy on the way."""
    np.take(source, rows, axis=0, out=out, mode="clip")


class _Rows:
    """A growing (n, width) array, rows appended in place, in memory that grows where it
    is (``mremap``: no copy of what is there, no page of it touched twice; the capacity
    doubles, untouched pages cost nothing); :meth:`rows` gives them, and ends the growing.

    A numpy array grown by copying touched its data about three times over: on this
    machine a process's first touch of memory costs about 2 ms a MB, and the welder's
    appends took 1.5 s for 15.7 M triangles against 0.1 s grown in place."""

    def __init__(self, width: int, dtype: np.dtype) -> None:
        self.width, self.dtype = width, np.dtype(dtype)
        self.row_bytes = width * self.dtype.itemsize
        self.memory: mmap.mmap | None = None
        self.count = self.capacity = 0

    def __len__(self) -> int:
        return self.count

    def extend(self, n: int, fill: Callable[[np.ndarray], object]) -> None:
        """Append ``n`` rows that ``fill(out)`` writes into ``out``."""
        need = self.count + n
        if self.row_bytes == 0 or n == 0:
            self.count = need
            return
        if need > self.capacity:
            self._grow(max(need, 2 * self.capacity, 1 << 16))
        assert self.memory is not None
        rows = np.frombuffer(self.memory, self.dtype, count=need * self.width)
        fill(rows.reshape(need, self.width)[self.count :])
        del rows  # the memory may move on the next growth: no view of it may outlive this
        self.count = need

    def _grow(self, capacity: int) -> None:
        size = capacity * self.row_bytes
        if self.memory is None:
            self.memory = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
        else:
            try:
                self.memory.resize(size)
            except (OSError, SystemError, ValueError):  # no mremap here: copy it over
                grown = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
                grown[: self.count * self.row_bytes] = self.memory[: self.count * self.row_bytes]
                self.memory.close()
                self.memory = grown
        if hasattr(self.memory, "madvise") and hasattr(mmap, "MADV_HUGEPAGE"):
            self.memory.madvise(mmap.MADV_HUGEPAGE)  # as numpy asks for its large arrays
        self.capacity = capacity

    def take(self, index: np.ndarray) -> np.ndarray:
        """A copy of the rows at ``index`` (no view of this memory leaves: it may move)."""
        if self.memory is None or self.count == 0:
            return np.empty((len(index), self.width), dtype=self.dtype)
        return self._current()[index]

    def put(self, index: np.ndarray, values: np.ndarray) -> None:
        """Overwrite the rows at ``index`` with ``values``."""
        if self.memory is not None and self.count and len(index):
            self._current()[index] = values

    def _current(self) -> np.ndarray:
        assert self.memory is not None  # callers look first
        rows = np.frombuffer(self.memory, self.dtype, count=self.count * self.width)
        return rows.reshape(self.count, self.width)

    def rows(self) -> np.ndarray:
        """The rows (a view of this memory, trimmed to them); no more may be appended."""
        if self.memory is None or self.count == 0:
            return np.empty((self.count, self.width), dtype=self.dtype)
        if self.capacity > self.count:
            with suppress(OSError, SystemError, ValueError, BufferError):  # else: spare room
                self.memory.resize(self.count * self.row_bytes)
                self.capacity = self.count
        return self._current()
