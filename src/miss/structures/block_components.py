"""A level's connected components block by block: the volume is never whole in memory.

The same components, the same choice and the same surfaces as the in-memory path
(:func:`miss.structures.components.select_components`, then one surface per group with
the other pieces blanked), for a volume read lazily (a ``zarr.Array``, a
:class:`~miss.surface.blockwise.StridedView` of one). Three passes of independent tasks
(:func:`miss.surface.runner.run_blocks`, threads or Dask; a :class:`~miss.surface.blocks.Grid` travels,
never the voxels):

1. **Labels.** The padded grid's points are cut into *owned* boxes that tile it (the
   surface blocks' boxes, each without its last plane of points). Each task labels its
   box's ``> level`` voxels with 26-connectivity (``scipy.ndimage.label``) and returns the
   labels' voxel counts, first voxels (C order, as ``ndimage.label`` numbers them),
   bounding boxes and its labels on its face planes (two on the low side, one on the high
   side of each axis); never the label volume.
2. **Seams.** Two voxels of different boxes that touch (face, edge or corner) lie on the
   two planes either side of a cut along some axis, at most one apart in the other two:
   comparing each cut's two planes under the nine shifts joins every such pair. A graph
   of the labels (``scipy.sparse.csgraph.connected_components``) then gives the global
   components; numbered by first voxel they are ``ndimage.label``'s ids, so ties are
   broken alike.
3. **Surfaces.** One wave per group of chosen components (all of them, or one each with
   ``split``): each surface block relabels its owned box (the same labels as pass 1),
   takes the pieces of the planes around it from the seams, blanks the voxels of the
   components not in the group (to the data type's minimum) and everything outside the
   group's box grown by one voxel (the in-memory path's crop), and runs flying edges;
   blocks outside that box are not run. Welding is exact as for any blockwise surface
   (:mod:`miss.surface.blocks`).

Integer data gives the in-memory path's triangles and vertices (to float32 rounding).
Float data is labelled as float32, as its surfaces are read; where a piece meets the
region's faces its cap vertices move by a few 1e-5 mm, as the pad below the level goes
as deep as the whole region's span here and the crop's in memory.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np

from miss.errors import EmptySurface
from miss.structures.components import _CONNECTIVITY, Components, choose_components
from miss.surface import check_level, contour_level, pad_value
from miss.surface.blocks import Box, Grid, Welder, read_points
from miss.surface.blockwise import (
    BlockShape,
    Progress,
    block_edges,
    block_source,
    counted,
    surface_task,
)
from miss.surface.runner import CLUSTER_VOXELS, run_blocks, scheduler_address
from miss.types import Mesh, Volume

#: Face planes a labelled box keeps on its low and high side of each axis: a surface block
#: reads one plane before its box and two after (its last plane and the gradients' one).
LOW_PLANES, HIGH_PLANES = 2, 1

#: The share of a job's surface progress that labelling the boxes takes (the surfaces of
#: the chosen groups share the rest).
LABELS_SHARE = 0.3


@dataclass(frozen=True)
class Labelled:
    """One owned box's labels, without the label volume.

    Attributes
    ----------
    count : int
        Labels in the box (1 .. count; 0 is outside the level).
    sizes : (count + 1,) int64 array
        Voxels per label.
    first : (count,) int64 array
        The region's C-order index of each label's first voxel.
    lo, hi : (count, 3) int64 arrays
        Each label's bounding box, padded-grid points, inclusive.
    planes : list of (Box, int32 array)
        The labels on the box's face planes (:data:`LOW_PLANES`, :data:`HIGH_PLANES`).
    span : (float, float)
        The smallest and largest region voxel in the box.
    """

    count: int
    sizes: np.ndarray
    first: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    planes: list[tuple[Box, np.ndarray]]
    span: tuple[float, float]


@dataclass(frozen=True)
class Chosen:
    """Components chosen block by block: the voxel groups to make surfaces of (global
    ids, one group, or one a component with ``split``), their voxel counts, how many
    components were left out, and what the surface blocks need: the labelling
    (:class:`_Labels`) and the grid they contour (its pad below the level)."""

    groups: list[list[int]]
    sizes: list[int]
    dropped: int
    labels: _Labels
    grid: Grid


@dataclass(frozen=True)
class _Labels:
    """The labelling's result on the driver: the owned boxes, each one's first
    provisional id (``offsets``; a box's label ``l`` is ``offsets[b] + l``) and label
    count, the global
    component of each provisional id (0: none), each component's bounding box (padded
    points), and the planes either side of every cut (provisional ids), per axis:
    ``seams[k][c]`` holds planes ``c - 1``, ``c`` and ``c + 1`` across the whole grid."""

    owned: list[Box]
    offsets: np.ndarray
    counts: np.ndarray
    component: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    seams: list[dict[int, np.ndarray]]


def owned_boxes(padded: Sequence[int], edges: Sequence[int]) -> list[Box]:
    """Boxes of points that tile the padded grid: the surface blocks'
    (:func:`miss.surface.blocks.cell_blocks`) without their last plane, save the last box's.
    Edges under 2 become 2, so that every box holds the planes its neighbours read."""
    ranges = []
    for n, e in zip(padded, edges, strict=True):
        cuts = [*range(0, n - 1, max(2, e)), n - 1]
        ranges.append([(a, b - 1) for a, b in itertools.pairwise(cuts)])
        ranges[-1][-1] = (ranges[-1][-1][0], n - 1)
    return [tuple(box) for box in itertools.product(*ranges)]


def cell_box(owned: Box, padded: Sequence[int]) -> Box:
    """The surface block's box of cells over an owned box: one plane further up."""
    return tuple((a, min(b + 1, n - 1)) for (a, b), n in zip(owned, padded, strict=True))


def _region_mask(grid: Grid, box: Box, level: float) -> tuple[np.ndarray, tuple[float, float]]:
    """The voxels of ``box`` above ``level`` (the pad never is), and their min and max."""
    points = read_points(grid, box)
    inner = tuple(
        slice(max(a, 1) - a, min(b, n) - a + 1) for (a, b), n in zip(box, grid.shape, strict=True)
    )
    mask = np.zeros(points.shape, dtype=bool, order="F")
    voxels = points[inner]
    mask[inner] = voxels > level
    span = (float(voxels.min()), float(voxels.max())) if voxels.size else (np.inf, -np.inf)
    return mask, span


def _label_box(mask: np.ndarray) -> tuple[np.ndarray, int]:
    from scipy import ndimage

    return ndimage.label(mask, structure=_CONNECTIVITY, output=np.int32)


def label_task(grid: Grid, box: Box, level: float) -> Labelled:
    """Pass 1 for one owned box (see the module's note)."""
    from scipy import ndimage

    mask, span = _region_mask(grid, box, level)
    labels, count = _label_box(mask)
    sizes = np.bincount(labels.ravel(order="K"), minlength=count + 1).astype(np.int64)
    origin = np.array([a for a, _ in box], dtype=np.int64)
    slices = ndimage.find_objects(labels)
    lo = np.array([[s.start for s in sl] for sl in slices], np.int64).reshape(-1, 3) + origin
    hi = np.array([[s.stop - 1 for s in sl] for sl in slices], np.int64).reshape(-1, 3) + origin
    # ndimage numbers labels by first voxel in C order, the box's C order is the region's
    # restricted to it: a label's first voxel is where the running maximum first rises
    flat = labels.ravel(order="C")
    rises = np.flatnonzero(flat > np.maximum.accumulate(np.concatenate([[0], flat[:-1]])))
    voxel = np.stack(np.unravel_index(rises, labels.shape), axis=1) + origin - 1
    first = np.ravel_multi_index(voxel.T, grid.shape) if count else np.zeros(0, np.int64)
    return Labelled(count, sizes, first.astype(np.int64), lo, hi, _face_planes(labels, box), span)


def _face_planes(labels: np.ndarray, box: Box) -> list[tuple[Box, np.ndarray]]:
    """The labels on the box's low (:data:`LOW_PLANES`) and high (:data:`HIGH_PLANES`)
    face planes of each axis, with where they lie."""
    out = []
    for k, (a, b) in enumerate(box):
        for lo, hi in ((a, min(a + LOW_PLANES - 1, b)), (max(b - HIGH_PLANES + 1, a), b)):
            sub = tuple((lo, hi) if j == k else ab for j, ab in enumerate(box))
            out.append((sub, np.ascontiguousarray(labels[_within(sub, box)])))
    return out


def _within(sub: Box, box: Box) -> tuple[slice, ...]:
    """``sub``'s place in an array read over ``box`` (both padded points, inclusive)."""
    return tuple(slice(s - a, t - a + 1) for (s, t), (a, _) in zip(sub, box, strict=True))


def _overlap(one: Box, other: Box) -> Box | None:
    both = tuple((max(a, c), min(b, d)) for (a, b), (c, d) in zip(one, other, strict=True))
    return None if any(a > b for a, b in both) else both


def blockwise_components(
    volume: Volume,
    level: float,
    components: Components | str,
    min_voxels: float,
    max_parts: int,
    *,
    block: BlockShape = None,
    scheduler: str | None = None,
    cluster: bool | None = None,
    progress: Progress | None = None,
) -> Chosen:
    """The components of ``volume.data > level`` chosen as
    :func:`~miss.structures.components.select_components` chooses them (the same ids,
    order, ties, minimum size, ``max_parts`` and count left out), block by block.

    ``volume.data`` is any 3-D array that slices like numpy (read a box at a time);
    ``block`` the block edge in cells (int or (x, y, z), at least 2), ``scheduler`` and
    ``cluster`` as for :func:`miss.surface.blockwise.blockwise_surface`; ``progress("surface",
    fraction)`` counts the boxes labelled up to :data:`LABELS_SHARE`.
    """
    dtype = np.dtype(volume.data.dtype)
    data, start, step = block_source(volume.data, (0, 0, 0), (1, 1, 1))
    shape = tuple(int(n) for n in volume.data.shape)
    contour = contour_level(dtype, level)
    # read as the surfaces will be (float data as float32), so that they label alike; the
    # pad is left out of the labels, its value not needed yet
    read_as = np.dtype(pad_value(dtype, contour, 0.0)[0]).str
    grid = Grid(data, start, step, shape, 0.0, read_as)  # type: ignore[arg-type]
    owned = owned_boxes(grid.padded, block_edges(block))
    run = _runner(scheduler, cluster, shape)
    found: list[Labelled | None] = [None] * len(owned)
    index = {box: i for i, box in enumerate(owned)}
    done = None if progress is None else partial(counted, progress, 0.0, LABELS_SHARE)
    for box, part in run(partial(_label_item, level=level), grid, owned, progress=done):
        found[index[box]] = part
    parts: list[Labelled] = [p for p in found if p is not None]
    check_level(level, min(p.span[0] for p in parts), max(p.span[1] for p in parts))
    labels, sizes = _joined(grid, owned, parts)
    kept, dropped = choose_components(sizes, components, min_voxels, max_parts)
    groups = [[c] for c in kept] if components == "split" else [kept] if kept else []
    span = max(p.span[1] for p in parts) - min(p.span[0] for p in parts)
    pad_dtype, pad = pad_value(dtype, contour, span)
    surface_grid = Grid(data, start, step, shape, pad, np.dtype(pad_dtype).str)  # type: ignore[arg-type]
    return Chosen(groups, [int(sizes[i]) for i in kept], dropped, labels, surface_grid)


def _runner(scheduler: str | None, cluster: bool | None, shape: Sequence[int]) -> Any:
    """:func:`miss.surface.runner.run_blocks` set up as :func:`miss.surface.blockwise.blockwise_surface`
    sets it up."""
    big = cluster if cluster is not None else int(np.prod(shape)) >= CLUSTER_VOXELS
    return partial(run_blocks, scheduler=scheduler_address(scheduler), cluster=big)


def _label_item(grid: Grid, box: Box, level: float) -> tuple[Box, Labelled]:
    """:func:`label_task` with its box: results arrive in any order."""
    return box, label_task(grid, box, level)


def _joined(grid: Grid, owned: list[Box], parts: list[Labelled]) -> tuple[_Labels, np.ndarray]:
    """Pass 2: the boxes' labels joined across the cuts into global components, numbered
    by first voxel (``ndimage.label``'s ids), and their voxel counts (index 0: none)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    counts = np.array([p.count for p in parts], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
    total = int(counts.sum())
    seams = [_seam_planes(grid.padded, k, owned, parts, offsets) for k in range(3)]
    pairs = [_touching(planes, k) for k in range(3) for planes in seams[k].values()]
    a, b = (np.concatenate([p[i] for p in pairs] or [np.zeros(0, np.int64)]) for i in (0, 1))
    graph = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(total + 1, total + 1))
    _, joined = connected_components(graph, directed=False)
    joined = joined[1:]  # provisional ids 1 .. total
    roots, which = np.unique(joined, return_inverse=True)
    first = np.full(len(roots), np.iinfo(np.int64).max, dtype=np.int64)
    np.minimum.at(first, which, np.concatenate([p.first for p in parts] or [first[:0]]))
    number = np.empty(len(roots), dtype=np.int64)
    number[np.argsort(first, kind="stable")] = np.arange(1, len(roots) + 1)
    ids = number[which]
    sizes = np.zeros(len(roots) + 1, dtype=np.int64)
    np.add.at(sizes, ids, np.concatenate([p.sizes[1:] for p in parts] or [sizes[:0]]))
    lo = np.full((len(roots) + 1, 3), np.iinfo(np.int64).max, dtype=np.int64)
    hi = np.full((len(roots) + 1, 3), -1, dtype=np.int64)
    np.minimum.at(lo, ids, np.concatenate([p.lo for p in parts]))
    np.maximum.at(hi, ids, np.concatenate([p.hi for p in parts]))
    component = np.concatenate([[0], ids])
    return _Labels(owned, offsets, counts, component, lo, hi, seams), sizes


def _seam_planes(
    padded: tuple[int, int, int],
    k: int,
    owned: list[Box],
    parts: list[Labelled],
    offsets: np.ndarray,
) -> dict[int, np.ndarray]:
    """Planes ``c - 1``, ``c`` and ``c + 1`` of every cut ``c`` along axis ``k`` (where an
    owned box starts), across the grid, in provisional ids (0: below the level): each box's
    low planes go to the cut at its start, its high plane to the cut after its end."""
    out: dict[int, np.ndarray] = {}
    seams: dict[int, Box] = {}
    for c in sorted({box[k][0] for box in owned} - {0}):
        seams[c] = tuple((c - 1, c + 1) if j == k else (0, n - 1) for j, n in enumerate(padded))
        out[c] = np.zeros([b - a + 1 for a, b in seams[c]], dtype=np.int64)
    for box, part, offset in zip(owned, parts, offsets, strict=True):
        low, high = part.planes[2 * k], part.planes[2 * k + 1]
        for (sub, labels), c in ((low, box[k][0]), (high, box[k][1] + 1)):
            if c in seams:
                both = _overlap(sub, seams[c])
                if both is not None:
                    local = labels[_within(both, sub)]
                    out[c][_within(both, seams[c])] = np.where(local > 0, local + offset, 0)
    return out


def _touching(planes: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of provisional ids that touch across a cut: plane ``c - 1`` against plane
    ``c``, each voxel against its nine neighbours (face, edge and corner)."""
    below, above = np.take(planes, 0, axis=k), np.take(planes, 1, axis=k)
    found = []
    for d0, d1 in itertools.product((-1, 0, 1), repeat=2):
        s0, t0 = _shifted(below.shape[0], d0)
        s1, t1 = _shifted(below.shape[1], d1)
        a, b = below[s0, s1], above[t0, t1]
        both = (a > 0) & (b > 0)
        found.append(np.stack([a[both], b[both]]))
    pairs = np.unique(np.concatenate(found, axis=1), axis=1)
    return pairs[0], pairs[1]


def _shifted(n: int, d: int) -> tuple[slice, slice]:
    """Slices pairing index ``i`` with ``i + d`` over ``0 .. n - 1``."""
    return slice(max(0, -d), n - max(0, d)), slice(max(0, d), n - max(0, -d))


@dataclass(frozen=True)
class _PartBlock:
    """What one surface block of one group needs beyond the grid: its box of cells, its
    owned box and which of that box's labels are in the group (``keep``, by local label),
    the voxels to blank around it (``shell``: boxes of padded points, a bool array each)
    and the group's box grown by one voxel (``crop``: outside it, the pad)."""

    box: Box
    owned: Box
    keep: np.ndarray
    shell: list[tuple[Box, np.ndarray]]
    crop: Box


def component_surfaces(
    volume: Volume,
    level: float,
    chosen: Chosen,
    *,
    normals: bool = True,
    scheduler: str | None = None,
    cluster: bool | None = None,
    progress: Progress | None = None,
) -> list[Mesh]:
    """Pass 3: the surface of each of ``chosen.groups``, block by block, in LPS mm: the
    triangles and vertices (to float32 rounding) of the in-memory path's surfaces
    (:func:`miss.structures.build._component_surface` on the whole volume).
    ``progress("surface", fraction)`` counts the blocks from :data:`LABELS_SHARE` on."""
    grid, labels = chosen.grid, chosen.labels
    run = _runner(scheduler, cluster, grid.shape)
    task = partial(
        _part_task, level=level, contour=contour_level(np.dtype(volume.data.dtype), level),
        normals=normals, affine=volume.affine,
    )  # fmt: skip
    meshes = []
    width = (1.0 - LABELS_SHARE) / max(len(chosen.groups), 1)
    for n, group in enumerate(chosen.groups):
        welder = Welder()
        start = LABELS_SHARE + n * width
        done = None if progress is None else partial(counted, progress, start, width)
        for part in run(task, grid, _part_blocks(grid, labels, group), progress=done):
            welder.add(part, part.vertices, part.normals)
        verts, faces, vectors = welder.result()
        if len(faces) == 0:
            raise EmptySurface(f"no surface at level {level:g} around the chosen pieces.")
        if np.linalg.det(volume.affine[:3, :3]) < 0:
            faces = np.ascontiguousarray(faces[:, ::-1])  # a mirroring affine flips the winding
        meshes.append(Mesh(vertices=verts, faces=faces, normals=vectors if normals else None))
    return meshes


def _part_blocks(grid: Grid, labels: _Labels, group: list[int]) -> list[_PartBlock]:
    """The surface blocks of one group: those whose cells meet the group's crop."""
    keep = np.isin(labels.component, group)
    keep[0] = False
    lo, hi = labels.lo[group].min(axis=0), labels.hi[group].max(axis=0)
    crop = tuple(
        (max(int(a) - 1, 1), min(int(b) + 1, n)) for a, b, n in zip(lo, hi, grid.shape, strict=True)
    )
    out = []
    ends = [n - 1 for n in grid.padded]
    for owned, offset, count in zip(labels.owned, labels.offsets, labels.counts, strict=True):
        box = cell_box(owned, grid.padded)
        if _overlap(box, crop) is None:
            continue
        read = tuple((max(a - 1, 0), min(b + 1, e)) for (a, b), e in zip(box, ends, strict=True))
        shell = []
        for k, ((a, b), (r0, r1)) in enumerate(zip(owned, read, strict=True)):
            if a > 0:  # the plane before the box: the last of the box below
                shell.append(_blanks(labels.seams[k][a], a, k, (a - 1, r0), read, keep))
            if b < ends[k]:  # the planes after it: the first two of the box above
                shell.append(_blanks(labels.seams[k][b + 1], b + 1, k, (b + 1, r1), read, keep))
        local = keep[offset : offset + count + 1].copy()
        local[0] = False
        out.append(_PartBlock(box, owned, local, shell, crop))
    return out


def _blanks(
    seam: np.ndarray, cut: int, k: int, along: tuple[int, int], read: Box, keep: np.ndarray
) -> tuple[Box, np.ndarray]:
    """The voxels of the cut's planes ``along`` axis ``k`` (within the block's ``read``
    box) that belong to components outside the group."""
    sub = tuple(along if j == k else r for j, r in enumerate(read))
    where = tuple(
        slice(p0 - (cut - 1), p1 - (cut - 1) + 1) if j == k else slice(p0, p1 + 1)
        for j, (p0, p1) in enumerate(sub)
    )
    ids = seam[where]
    return sub, (ids > 0) & ~keep[ids]


def _part_task(
    grid: Grid,
    item: _PartBlock,
    level: float,
    contour: float,
    normals: bool,
    affine: np.ndarray,
) -> Any:
    """One surface block of one group, its other pieces blanked, in LPS mm."""
    edit = partial(_blank, item=item, level=level, low=grid.pad)
    zero = np.zeros(3)
    return surface_task(grid, item.box, contour, normals, affine, (1, 1, 1), zero, edit)


def _blank(points: np.ndarray, read: Box, item: _PartBlock, level: float, low: float) -> np.ndarray:
    """``points`` (read over ``read``) with the voxels of components outside the group and
    everything outside the group's crop set to ``low``. The owned box is labelled again:
    the same data, the same labels as :func:`label_task` gave."""
    inside = _within(item.owned, read)
    owned = points[inside]  # a view
    labels, _ = _label_box(owned > level)  # the pad never reaches the level
    owned[(labels > 0) & ~item.keep[labels]] = low
    for sub, blank in item.shell:
        both = _overlap(sub, read)
        if both is not None:
            view = points[_within(both, read)]
            view[blank[_within(both, sub)]] = low
    for k, ((c0, c1), (a, _)) in enumerate(zip(item.crop, read, strict=True)):
        before = [slice(None)] * 3
        before[k] = slice(0, max(c0 - a, 0))
        points[tuple(before)] = low
        after = [slice(None)] * 3
        after[k] = slice(max(c1 + 1 - a, 0), None)
        points[tuple(after)] = low
    return points
