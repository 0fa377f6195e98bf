"""``blockwise_surface``: :func:`miss.surface.extract_surface` computed block by block.

Two passes over the blocks, each a set of independent tasks (:mod:`miss.surface.runner`): the
region's minimum and maximum (the level must lie between them; float data's pad value
depends on the span), then the surface of each block (:mod:`miss.surface.blocks`). Each block's
mesh is mapped to LPS millimetres as it arrives and welded at the end.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import partial
from typing import Any, NamedTuple

import numpy as np

from miss.errors import BadParameter, EmptySurface
from miss.surface import (
    Roi,
    SampleRate,
    _normals_to_patient,
    _points_to_patient,
    check_level,
    checked_region,
    contour_level,
    extract_surface,
    pad_value,
)
from miss.surface.blocks import (
    BlockMesh,
    Box,
    Decimated,
    Edit,
    Grid,
    Welder,
    block_range,
    cell_blocks,
    done_with,
    surface_block,
    voxel_boxes,
)
from miss.surface.runner import CLUSTER_VOXELS, run_blocks, scheduler_address
from miss.types import Mesh, StridedView, Volume, memory_budget

#: Block edge in cells when none is asked for: 128³ cells, ~2 M voxels (4 MB of int16)
#: plus VTK's working arrays per task, well under a worker's memory.
AUTO_BLOCK = 128

#: Block edge of the min/max pass (a read and two reductions per task).
RANGE_BLOCK = 256

BlockShape = int | Sequence[int] | None
Progress = Callable[[str, float], None]


def block_edges(block: BlockShape) -> tuple[int, int, int]:
    """(ex, ey, ez) cells per block from an int, three ints, or None (auto)."""
    given: Any = block  # checked here whatever it is: it comes from a user
    edges = (
        (AUTO_BLOCK,) * 3 if given is None else (given,) * 3 if np.isscalar(given) else tuple(given)
    )
    if len(edges) != 3 or any(int(e) != e or e < 1 for e in edges):
        raise BadParameter(
            f"block size needs one whole number >= 1 or three (x,y,z), got {block!r}."
        )
    return int(edges[0]), int(edges[1]), int(edges[2])


@dataclass(frozen=True)
class BlockDecimation:
    """Decimate each block where it was made, its border vertices held (so that the blocks
    still meet), before the blocks are welded: the job's ``method``, ``reduce`` and
    ``error_bound`` (a fraction of the whole surface's diagonal, as ever). A block gets
    :data:`BLOCK_BOUND_SHARE` of the bound and keeps :data:`BLOCK_KEEP` times the job's
    share of its triangles; what is left is spent across the blocks (the job's
    ``decimate`` on the welded mesh)."""

    method: str
    reduce: float
    error_bound: float


#: The share of the error bound the blocks may spend; the pass across them gets the rest
#: (what the blocks did not use, measured).
BLOCK_BOUND_SHARE = 0.5
#: Blocks keep this many times the job's final share of their triangles (the pass across
#: the blocks removes the rest, borders included): as the slabs of ``decimate.quadric``.
BLOCK_KEEP = 2.0


@dataclass(frozen=True)
class BlockStage:
    """What decimating the blocks did: triangles before (the full surface) and after,
    the whole surface's diagonal (mm), the bound the blocks had and their measured
    maximum and mean (triangle-weighted) deviation, mm, and the seconds it took."""

    triangles_in: int
    triangles_out: int
    diagonal_mm: float
    bound_mm: float
    max_mm: float
    mean_mm: float
    #: from the blocks' extents known to the welded mesh (their surfaces' time not counted)
    seconds: float


def blockwise_surface(
    volume: Volume,
    level: float,
    sample_rate: SampleRate = 1,
    slices: tuple[int, int] | None = None,
    roi: Roi | None = None,
    *,
    normals: bool = True,
    block: BlockShape = None,
    scheduler: str | None = None,
    cluster: bool | None = None,
    progress: Progress | None = None,
) -> Mesh:
    """The closed isosurface of ``extract_surface(volume, level, ...)``, block by block.

    ``volume.data`` may be any 3-D array that slices like numpy (a ``zarr.Array`` on disk
    is read block by block, never whole). ``block`` is the block edge in cells (int or
    (x, y, z)); ``scheduler`` a Dask address (default ``MISS_DASK_SCHEDULER``); ``cluster``
    forces (True) or forbids (False) a local Dask cluster, by default used from
    :data:`miss.surface.runner.CLUSTER_VOXELS` voxels. ``progress("surface", fraction)`` counts
    blocks. The same triangles and vertices as one flying-edges pass over the padded
    region, vertices placed from float64 edge parameters (see :mod:`miss.surface.blocks`).
    """
    mesh, _, _ = _blockwise(
        volume, level, sample_rate, slices, roi, normals=normals, block=block,
        scheduler=scheduler, cluster=cluster, progress=progress, decimation=None,
    )  # fmt: skip
    return mesh


def blockwise_decimated(
    volume: Volume,
    level: float,
    decimation: BlockDecimation,
    *,
    block: BlockShape = None,
    scheduler: str | None = None,
    cluster: bool | None = None,
    progress: Progress | None = None,
) -> tuple[Mesh, BlockStage]:
    """:func:`blockwise_surface` (no normals) with each block decimated where it was made,
    its border held: the welded mesh, still to be decimated across the blocks, and what
    the blocks did. The full-resolution surface is never in one place: each block's stays
    in the process (or Dask worker) that made it until the bound, which needs the whole
    surface's diagonal, is known from every block's extent (a second wave of tasks).

    Each block's output is measured against its own full-resolution surface
    (:func:`miss.decimate.decimate_held`); the blocks tile the surface, so the welded mesh
    lies within the largest block's measured deviation of it, both ways.
    """
    mesh, parts, began = _blockwise(
        volume, level, normals=False, block=block, scheduler=scheduler, cluster=cluster,
        progress=progress, decimation=decimation,
    )  # fmt: skip
    assert parts is not None
    before = sum(p.triangles_in for p in parts)
    diagonal = _diagonal(parts)
    stage = BlockStage(
        triangles_in=before,
        triangles_out=mesh.n_triangles,
        diagonal_mm=diagonal,
        bound_mm=BLOCK_BOUND_SHARE * decimation.error_bound * diagonal,
        max_mm=max((p.max_mm for p in parts), default=0.0),
        mean_mm=sum(p.mean_mm * p.triangles_in for p in parts) / max(before, 1),
        seconds=time.perf_counter() - began,
    )
    return mesh, stage


def _diagonal(extents: Sequence[Any]) -> float:
    """The diagonal (mm) of the box around every block's ``lo`` .. ``hi``."""
    used = [e for e in extents if np.all(e.lo <= e.hi)]
    if not used:
        return 0.0
    lo = np.min([e.lo for e in used], axis=0)
    hi = np.max([e.hi for e in used], axis=0)
    return float(np.linalg.norm(hi - lo))


def _blockwise(
    volume: Volume,
    level: float,
    sample_rate: SampleRate = 1,
    slices: tuple[int, int] | None = None,
    roi: Roi | None = None,
    *,
    normals: bool,
    block: BlockShape,
    scheduler: str | None,
    cluster: bool | None,
    progress: Progress | None,
    decimation: BlockDecimation | None,
) -> tuple[Mesh, list[Decimated] | None, float]:
    """The welded surface; with ``decimation`` (blocks decimated where they were made),
    what each block's decimation did, and when it began (``time.perf_counter``)."""
    steps, box, shape = checked_region(volume.dims, level, sample_rate, slices, roi)
    dtype = np.dtype(volume.data.dtype)
    data, start, step = block_source(volume.data, [lo for lo, _ in box], steps)
    grid = Grid(data, start, step, shape, 0.0, dtype.str)  # type: ignore[arg-type]
    blocks = cell_blocks(grid.padded, block_edges(block))
    address = scheduler_address(scheduler)
    big = cluster if cluster is not None else int(np.prod(shape)) >= CLUSTER_VOXELS
    run = partial(run_blocks, scheduler=address, cluster=big)
    report = progress or (lambda stage, fraction: None)
    contour = contour_level(dtype, level)
    # Integer data pads with its type's minimum: the surface pass needs no value range
    # first, and each block reports its own (checked once all are in). Float data's pad
    # lies below the range, which a first pass finds (big blocks, few tasks).
    in_one_pass = np.issubdtype(dtype, np.integer) and np.iinfo(dtype).min < contour
    lo, hi, progress_from = np.inf, -np.inf, 0.0
    if not in_one_pass:
        lo, hi = _range(grid, voxel_boxes(grid, RANGE_BLOCK), run, report)
        check_level(level, lo, hi)
        progress_from = 0.1
    pad_dtype, pad = pad_value(dtype, contour, hi - lo if not in_one_pass else 0.0)
    grid = Grid(grid.data, grid.start, grid.step, grid.shape, pad, np.dtype(pad_dtype).str)
    offset = np.array([b[0] for b in box], dtype=np.float64)
    # On threads the blocks come in their order and are welded at the end; from Dask, as
    # they come, and where the model is decimated across the blocks next, renumbered to
    # the blocks' order: the decimation depends on it, and the same volume then makes the
    # same model every run, on threads or any cluster
    welder = Welder(as_they_come=address is not None or big, in_order=decimation is not None)
    order = {box: i for i, box in enumerate(blocks)}
    # each task maps its own vertices to mm: float32 travels back, and the work is spread
    task = partial(
        surface_task, level=contour, normals=normals, affine=volume.affine, steps=steps,
        offset=offset,
    )  # fmt: skip
    done = partial(_waves, report, progress_from, decimation is not None)
    second: list[float] = []  # when the blocks' decimation (the second wave) began
    then = None if decimation is None else (_extent, partial(_decide, decimation, second))
    stages: list[Decimated] | None = None if decimation is None else []
    for part in run(task, grid, blocks, progress=done, then=then):
        lo, hi = min(lo, part.span[0]), max(hi, part.span[1])
        welder.add(part, part.vertices, part.normals, order.get(part.box, -1))
        if stages is not None and part.decimated is not None:
            stages.append(part.decimated)
    check_level(level, lo, hi)
    verts, faces, index_normals = welder.result()
    if len(faces) == 0:
        raise EmptySurface(
            f"no surface at level {level:g} in the chosen region; pick another level."
        )
    if np.linalg.det(volume.affine[:3, :3]) < 0:
        faces = np.ascontiguousarray(faces[:, ::-1])  # a mirroring affine flips the winding
    mesh = Mesh(vertices=verts, faces=faces, normals=index_normals if normals else None)
    del welder, verts, faces, index_normals
    done_with(grid.data)
    return mesh, stages, second[0] if second else time.perf_counter()


def block_source(
    data: Any, start: Sequence[int], steps: Sequence[int]
) -> tuple[Any, tuple[int, ...], tuple[int, ...]]:
    """The array the blocks read, where the region starts in it and its steps: through a
    :class:`StridedView` to the array on disk itself, so that its chunks are read whole
    and kept (:data:`miss.surface.blocks.CHUNKS`)."""
    if isinstance(data, StridedView):
        inner = [lo + s0 * st for (lo, _), s0, st in zip(data.box, start, data.steps, strict=True)]
        steps = [a * b for a, b in zip(steps, data.steps, strict=True)]
        return data.data, tuple(inner), tuple(steps)
    return data, tuple(start), tuple(steps)


def surface_task(
    grid: Grid,
    box: Box,
    level: float,
    normals: bool,
    affine: np.ndarray,
    steps: tuple[int, int, int],
    offset: np.ndarray,
    edit: Edit | None = None,
) -> BlockMesh:
    """One block's surface with its vertices (float32) and normals in LPS mm (``edit``: see
    :func:`miss.surface.blocks.surface_block`)."""
    part = surface_block(grid, box, level, normals, edit)
    verts = _points_to_patient(part.vertices - 1.0, affine, steps, offset)  # pad: -1
    vectors = part.normals
    if normals and len(vectors):
        vectors = _normals_to_patient(vectors, affine[:3, :3], steps)
    return replace(part, vertices=verts, normals=vectors, box=box)


class _Extent(NamedTuple):
    lo: np.ndarray
    hi: np.ndarray
    triangles: int


def _extent(part: BlockMesh) -> _Extent:
    """A block's full-resolution extent (mm) and triangles: what the bound needs."""
    if len(part.faces) == 0:
        return _Extent(np.full(3, np.inf), np.full(3, -np.inf), 0)
    v = part.vertices
    return _Extent(
        v.min(axis=0).astype(np.float64), v.max(axis=0).astype(np.float64), len(part.faces)
    )


def _decide(
    decimation: BlockDecimation, began: list[float], extents: list[_Extent]
) -> Callable[[BlockMesh], BlockMesh]:
    """Once every block's extent is known: each block's decimation, to its share of the
    bound (mm, from the whole surface's diagonal) and of the triangles (the time noted in
    ``began``)."""
    began.append(time.perf_counter())
    bound_mm = BLOCK_BOUND_SHARE * decimation.error_bound * _diagonal(extents)
    keep = min(1.0, BLOCK_KEEP * (1.0 - decimation.reduce))
    return partial(_decimate_block, method=decimation.method, reduce=1.0 - keep, bound_mm=bound_mm)


def _decimate_block(part: BlockMesh, method: str, reduce: float, bound_mm: float) -> BlockMesh:
    """``part`` decimated within ``bound_mm`` of itself (measured), its border vertices
    (``part.shared``) kept: they meet the neighbouring blocks'."""
    from miss.decimate import decimate_held

    lo, hi, count = _extent(part)
    if count == 0 or reduce <= 0.0:
        return replace(part, decimated=Decimated(0.0, 0.0, count, lo, hi))
    fixed = np.zeros(len(part.vertices), dtype=bool)
    fixed[part.shared] = True
    mesh = Mesh(vertices=part.vertices, faces=part.faces)
    vertices, faces, check = decimate_held(mesh, method, reduce, bound_mm, fixed)
    used = fixed.copy()
    used[faces.ravel()] = True
    new = np.cumsum(used) - 1
    return replace(
        part,
        # (a vertex the placed collapse moved keeps its normal: it moved less than the bound)
        vertices=np.asarray(vertices, dtype=part.vertices.dtype)[used],
        faces=new[faces].astype(np.int32),
        normals=part.normals[used],
        shared=new[part.shared],
        decimated=Decimated(check.max_mm, check.mean_mm, count, lo, hi),
    )


def _waves(report: Progress, start: float, decimating: bool, done: int, total: int) -> None:
    """Report ``done`` of ``total`` tasks: the surfaces' wave as "surface" from ``start``;
    with ``decimating``, the second wave (the blocks decimated) as the first half of
    "decimate" (what is left of it is done across the blocks)."""
    first = total // 2 if decimating else total
    if done <= first:
        counted(report, start, 1.0 - start, done, first)
    else:
        report("decimate", 0.5 * (done - first) / max(total - first, 1))


def counted(report: Progress, start: float, width: float, done: int, total: int) -> None:
    """Report ``done`` of ``total`` blocks as a fraction from ``start`` over ``width``."""
    report("surface", start + width * done / total)


def _range(
    grid: Grid, blocks: list[Box], run: Callable[..., object], report: Progress
) -> tuple[float, float]:
    """The region's minimum and maximum, block by block (the first tenth of the progress)."""
    lo, hi = np.inf, -np.inf
    for b_lo, b_hi in run(block_range, grid, blocks, progress=partial(counted, report, 0.0, 0.1)):  # type: ignore[attr-defined]
        lo, hi = min(lo, b_lo), max(hi, b_hi)
    return lo, hi


@dataclass(frozen=True)
class BlockRun:
    """How a job's surfaces run block by block: ``block`` edge in cells (None: auto),
    ``scheduler`` a Dask address (None: ``MISS_DASK_SCHEDULER``, else this machine), and
    the job's ``progress`` (it counts blocks)."""

    block: BlockShape = None
    scheduler: str | None = None
    progress: Progress | None = None


def in_blocks(volume: Volume, blocks: BlockRun | None) -> bool:
    """Whether a job's surfaces go block by block: ``blocks`` given, the volume's data
    not in memory (a ``zarr.Array``), or more bytes of it than the memory budget
    (:func:`miss.types.memory_budget`: one pass would need about three times them)."""
    data = volume.data
    return blocks is not None or not isinstance(data, np.ndarray) or data.nbytes > memory_budget()


def decimated_surface_of(
    volume: Volume, level: float, decimation: BlockDecimation, blocks: BlockRun | None
) -> tuple[Mesh, BlockStage]:
    """The job's surface stage with its blocks decimated where they were made
    (:func:`blockwise_decimated`)."""
    run = blocks or BlockRun()
    return blockwise_decimated(
        volume, level, decimation, block=run.block, scheduler=run.scheduler,
        progress=run.progress,
    )  # fmt: skip


def surface_of(
    volume: Volume, level: float, *, normals: bool, blocks: BlockRun | None = None
) -> Mesh:
    """The job's surface stage: block by block when :func:`in_blocks`, else
    :func:`~miss.surface.extract_surface`."""
    if not in_blocks(volume, blocks):
        return extract_surface(volume, level, normals=normals)
    run = blocks or BlockRun()
    return blockwise_surface(
        volume, level, normals=normals, block=run.block, scheduler=run.scheduler,
        progress=run.progress,
    )  # fmt: skip
