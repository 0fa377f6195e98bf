"""Isosurface extraction: marching cubes (VTK flying edges) in patient millimetres.

The surface is computed on the voxel index grid and mapped through the volume's
affine afterwards. Linear interpolation along cube edges commutes with affine maps,
so this is exact for sheared (gantry-tilted) and oblique grids alike.

Memory: the region is padded (so that cut surfaces close) and contoured slab by slab
along the third axis, each slab a small padded copy with one context plane beyond each
seam; the slabs' meshes are welded on the seams. The result is the one a single run over
the whole padded region gives (same triangles and normals), without a second copy of the
volume or VTK's whole-volume working arrays: the peak stays near the volume plus the mesh.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence

import numpy as np
from vtkmodules.util import numpy_support
from vtkmodules.vtkCommonCore import vtkSMPTools
from vtkmodules.vtkFiltersCore import vtkFlyingEdges3D

from miss._vtk import image_data
from miss.errors import BadParameter, EmptySurface
from miss.spec import Region
from miss.types import Mesh, Volume

SampleRate = int | Sequence[int]
_Arrays = tuple[np.ndarray, np.ndarray, np.ndarray]  # vertices, faces, normals
Roi = Sequence[int]  # (i0, i1, j0, j1, k0, k1), 0-based, inclusive


def pad_value(dtype: np.dtype, level: float, span: float) -> tuple[np.dtype, float]:
    """(dtype, value) of the pad: very low, so that the cap's vertices, interpolated towards
    it, land within a few hundredths of a voxel of the last chosen slice rather than half a
    voxel beyond. Integer data keeps its type when its minimum is below the level."""
    if np.issubdtype(dtype, np.integer) and np.iinfo(dtype).min < level:
        return dtype, float(np.iinfo(dtype).min)
    return np.dtype(np.float32), level - 1e3 * max(span, 1.0)


def _pad_below(block: np.ndarray, level: float, span: float) -> np.ndarray:
    """Surround the block by one voxel far below the level so cut surfaces close (capped)."""
    dtype, low = pad_value(block.dtype, level, span)
    out = np.full(tuple(s + 2 for s in block.shape), low, dtype=dtype, order="F")
    out[1:-1, 1:-1, 1:-1] = block
    return out


# Slabs of about this many voxels bound the padded copy and VTK's output (int64 triangles
# and a byte per voxel of edge cases) to a fraction of the volume: the peak stays near the
# volume's own bytes plus the mesh.
_SLAB_VOXELS = 4_000_000


def _seam_planes(block: np.ndarray, level: float) -> list[int]:
    """Planes (third axis) where the surface is cut into slabs, about ``_SLAB_VOXELS`` apart.

    A seam plane holds no voxel exactly at the level, so every vertex on it comes from an
    edge lying in the plane and is found, bit for bit the same, by the slabs on both sides.
    """
    nz = block.shape[2]
    depth = max(4, _SLAB_VOXELS // max(1, block.shape[0] * block.shape[1]))
    seams: list[int] = []
    for ideal in range(depth, nz - depth // 2, depth):
        for k in sorted(
            range(ideal - depth // 4, ideal + depth // 4 + 1), key=lambda k: abs(k - ideal)
        ):
            if seams and k <= seams[-1] + 2 or not 1 <= k <= nz - 2:
                continue
            if not (block[:, :, k] == level).any():
                seams.append(k)
                break
    return seams


def _slab(block: np.ndarray, first: int, last: int, pad: tuple[np.dtype, float]) -> np.ndarray:
    """Planes ``first..last`` of the block (-1 and nz stand for the pad) with the pad ring."""
    nx, ny, nz = block.shape
    out = np.full((nx + 2, ny + 2, last - first + 1), pad[1], dtype=pad[0], order="F")
    lo, hi = max(first, 0), min(last, nz - 1)
    out[1:-1, 1:-1, lo - first : hi - first + 1] = block[:, :, lo : hi + 1]
    return out


def contour_level(dtype: np.dtype, level: float) -> float:
    """The value flying edges contours: ``level``, a quarter below a whole-number level on
    integer data, or half a float32 step below a level float32 data can hold.

    Flying edges counts a voxel at or above the value as inside, and no integer lies between
    level - 1/4 and level, so inside and outside stay exactly as asked. What changes is that
    no vertex lands exactly on a voxel any more (t = 0 or 1 when a voxel equals the level):
    no coincident vertices, no zero-length edges, and every slab seam can be welded. A
    vertex moves by a quarter of a grey level over its edge's rise, 1/1000 voxel for a rise
    of 250.
    """
    if np.issubdtype(dtype, np.integer) and float(level).is_integer():
        return float(level) - 0.25
    if dtype in (np.float16, np.float32) and float(np.asarray(level, dtype)) == level:
        # float32 data may hold the level itself: contour halfway (in float64) to the next
        # float32 below, where no voxel value can lie, so no vertex sits on a voxel either
        below = np.nextafter(np.asarray(level, dtype), np.asarray(-np.inf, dtype))
        return (float(below) + float(level)) / 2
    return float(level)


class _SeamMismatch(Exception):
    """Two slabs disagree on a seam's vertices (float data at a knife's edge): don't weld."""


def _surface_whole(block: np.ndarray, level: float, span: float, normals: bool = True) -> _Arrays:
    """One padded copy, one flying-edges run; vertices in block index coordinates."""
    verts, faces, vertex_normals = _flying_edges(_pad_below(block, level, span), level, normals)
    verts -= np.float32(1.0)  # the pad shifted every index by one
    return verts, faces, vertex_normals


def _surface_in_slabs(
    block: np.ndarray, level: float, span: float, normals: bool = True
) -> _Arrays:
    """The padded block's surface, made slab by slab and welded along the seams.

    Each slab is copied with one context plane beyond each inner seam, so that the gradient
    normals on the seam are central differences as in one run over the whole block, and
    only the triangles of its own cells are kept. The result equals the whole block's (the
    same triangles, in another order); without a usable seam it *is* the whole-block run.
    """
    seams = _seam_planes(block, level)
    if not seams:
        return _surface_whole(block, level, span, normals)
    pad, bounds = pad_value(block.dtype, level, span), [-1, *seams, block.shape[2]]
    welder = _Welder()
    for j in range(len(bounds) - 1):
        inner_lo, inner_hi = j > 0, j < len(bounds) - 2
        first = bounds[j] - 1 if inner_lo else -1
        last = bounds[j + 1] + 1 if inner_hi else block.shape[2]
        verts, faces, slab_normals = _flying_edges(_slab(block, first, last, pad), level, normals)
        # seams in the slab's own (small) coordinates, where float32 still tells a vertex
        # a hair off the seam plane from one on it
        z_lo = bounds[j] - first if inner_lo else -np.inf
        z_hi = bounds[j + 1] - first if inner_hi else np.inf
        # context-layer triangles have a vertex beyond the seam: a marching-cubes triangle
        # never lies flat in a cell face, so each cell keeps exactly its own triangles
        beyond = (verts[:, 2] < z_lo) | (verts[:, 2] > z_hi)
        try:
            welder.add(verts, faces, slab_normals, beyond, (z_lo, z_hi))
        except _SeamMismatch:
            return _surface_whole(block, level, span, normals)
        welder.parts[-1][0][:] += np.array([-1.0, -1.0, first], dtype=np.float32)
    return welder.result()


class _Welder:
    """Concatenates slab meshes, giving a seam's vertices the ids they got in the slab below."""

    def __init__(self) -> None:
        self.parts: list[_Arrays] = []
        self.count = 0
        self.seam_xy = np.zeros((0, 2), dtype=np.float32)
        self.seam_ids = np.zeros(0, dtype=np.int64)

    def add(
        self,
        verts: np.ndarray,
        faces: np.ndarray,
        normals: np.ndarray,
        beyond: np.ndarray,
        seams: tuple[float, float],
    ) -> None:
        """Append one slab: triangles with a vertex ``beyond`` its seams are dropped, the
        vertices on its lower seam take their ids from the slab below."""
        ids = np.full(len(verts), -1, dtype=np.int64)
        if np.isfinite(seams[0]):
            below, xy = _seam_vertices(verts, seams[0])
            if not np.array_equal(xy, self.seam_xy):
                raise _SeamMismatch
            ids[below] = self.seam_ids
        kept, order = _keep_and_number(faces, beyond, ids, self.count)
        self.count += len(order)
        if np.isfinite(seams[1]):
            above, self.seam_xy = _seam_vertices(verts, seams[1])
            self.seam_ids = ids[above]
        self.parts.append((verts[order], kept, normals[order]))

    def result(self) -> _Arrays:
        verts, faces, normals = (np.concatenate([p[i] for p in self.parts]) for i in range(3))
        self.parts.clear()
        return verts, faces, normals


def _keep_and_number(
    faces: np.ndarray, beyond: np.ndarray, ids: np.ndarray, start: int
) -> tuple[np.ndarray, np.ndarray]:
    """Faces without a vertex ``beyond``, renumbered: vertices with an id (from the seam
    below) keep it, the others get start, start + 1, ... in first-use order. Returns the
    faces (int32) and the local indices of the newly numbered vertices; fills ``ids``.

    numpy here; numba's loop (:mod:`miss.surface._seams`) when numba is loaded already.
    """
    if "numba" in sys.modules:
        from miss.surface._seams import keep_and_number

        return keep_and_number(faces, beyond, ids, start)
    dropped = beyond[faces[:, 0]] | beyond[faces[:, 1]] | beyond[faces[:, 2]]
    flat = np.compress(~dropped, faces, axis=0).ravel()  # 8x faster than faces[mask] here
    first = np.full(len(ids), len(flat), dtype=np.int64)
    np.minimum.at(first, flat, np.arange(len(flat), dtype=np.int64))
    new = np.flatnonzero((ids < 0) & (first < len(flat)))
    at_first = np.zeros(len(flat) + 1, dtype=bool)
    at_first[first[new]] = True
    order = flat[at_first[:-1]]  # the new vertices in the order of their first use
    ids[order] = np.arange(start, start + len(order), dtype=ids.dtype)
    return ids[flat].astype(np.int32).reshape(-1, 3), order.astype(np.int64)


def _seam_vertices(verts: np.ndarray, plane: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the vertices on ``plane`` (exact: in-plane edges give integer z), sorted by
    (x, y), and their (x, y)."""
    on = np.flatnonzero(verts[:, 2] == np.float32(plane))
    xy = verts[on, :2]
    order = np.lexsort((xy[:, 1], xy[:, 0]))
    xy = xy[order]
    if len(xy) > 1 and (xy[1:] == xy[:-1]).all(axis=1).any():
        raise _SeamMismatch  # two vertices at one spot: their pairing would be a guess
    return on[order], xy


def checked_region(
    dims: Sequence[int],
    level: float,
    sample_rate: SampleRate,
    slices: tuple[int, int] | None,
    roi: Roi | None,
) -> tuple[tuple[int, int, int], list[tuple[int, int]], tuple[int, ...]]:
    """The sample steps, the region's voxel box and its sampled shape, checked by the job
    declaration's :class:`~miss.spec.Region` (its one check): a finite level and at least
    2 voxels per axis."""
    if not np.isfinite(level):
        raise BadParameter(f"level must be a finite number, got {level!r}.")
    start, end = slices if slices is not None else (None, None)
    rate = sample_rate if np.isscalar(sample_rate) else tuple(sample_rate)  # type: ignore[arg-type]
    voxels = None if roi is None else tuple(roi)
    region = Region(rate, start, end, voxels)  # type: ignore[arg-type]
    box = region.box(dims)
    steps = (int(region.steps[0]), int(region.steps[1]), int(region.steps[2]))
    shape = tuple(len(range(lo, hi + 1, st)) for (lo, hi), st in zip(box, steps, strict=True))
    return steps, box, shape


def check_level(level: float, lo: float, hi: float) -> None:
    """Refuse a level outside the region's values ``lo``..``hi`` (no surface there)."""
    if not lo < level < hi:
        raise EmptySurface(
            f"no surface at level {level:g}: the chosen region holds values {lo:g}..{hi:g}; "
            "pick a level inside that range."
        )


def extract_surface(
    volume: Volume,
    level: float,
    sample_rate: SampleRate = Region.sample_rate,
    slices: tuple[int, int] | None = None,
    roi: Roi | None = None,
    *,
    closed: bool = True,
    normals: bool = True,
) -> Mesh:
    """Marching-cubes isosurface of ``volume`` at ``level``, in LPS millimetres.

    Parameters
    ----------
    volume : Volume
    level : float
        Threshold in the volume's real units (HU for CT). Voxels above it are inside.
    sample_rate : int or (sx, sy, sz)
        Keep every n-th voxel along each axis (the paper's marching-cube size).
    slices : (start, end), optional
        1-based inclusive slice range along the third voxel axis (the paper's
        start and end slice).
    roi : (i0, i1, j0, j1, k0, k1), optional
        0-based inclusive voxel box.
    closed : bool
        Pad the region with one voxel below the level so that surfaces cut by the
        region's faces are capped and every surface is closed.
    normals : bool
        Compute gradient normals. A mesh that is decimated next gets new normals from its
        faces, so a caller that decimates can skip them (``normals`` is then None).

    Returns
    -------
    Mesh
        vertices (N, 3) float32 mm, faces (F, 3) int32 wound counter-clockwise seen
        from outside (from above-level towards below-level), outward unit normals.
    """
    steps, box, _ = checked_region(volume.dims, level, sample_rate, slices, roi)
    block = volume.data[
        tuple(slice(lo, hi + 1, st) for (lo, hi), st in zip(box, steps, strict=True))
    ]
    lo, hi = float(np.min(block)), float(np.max(block))
    check_level(level, lo, hi)
    offset = np.array([b[0] for b in box], dtype=np.float64)
    contour = contour_level(block.dtype, level)
    if closed:
        verts, faces, index_normals = _surface_in_slabs(block, contour, hi - lo, normals)
    else:
        verts, faces, index_normals = _flying_edges(np.asfortranarray(block), contour, normals)
    if len(faces) == 0:
        raise EmptySurface(
            f"no surface at level {level:g} in the chosen region; pick another level."
        )
    if np.linalg.det(volume.affine[:3, :3]) < 0:
        faces = np.ascontiguousarray(faces[:, ::-1])  # a mirroring affine flips the winding
    return Mesh(
        vertices=_points_to_patient(verts, volume.affine, steps, offset),
        faces=faces,
        normals=_normals_to_patient(index_normals, volume.affine[:3, :3], steps)
        if normals
        else None,
    )


def _map_rows(points: np.ndarray, matrix: np.ndarray, shift: np.ndarray, unit: bool) -> np.ndarray:
    """(N, 3) float32 ``points @ matrix.T + shift`` in float64 arithmetic, scaled to unit
    length when ``unit``.

    Column by column (a BLAS matmul of a tall (N, 3) array is slow and erratic: 0.05-0.3 s
    for 400 k rows here), each row's sums in the order ``m0 x + m1 y + m2 z + s``.
    """
    columns = [points[:, k].astype(np.float64) for k in range(3)]
    rows = []
    for r in range(3):
        row = columns[0] * matrix[r, 0]
        row += columns[1] * matrix[r, 1]
        row += columns[2] * matrix[r, 2]
        row += shift[r]
        rows.append(row)
    if unit:
        length = np.sqrt(rows[0] * rows[0] + rows[1] * rows[1] + rows[2] * rows[2])
        length[length == 0.0] = 1.0  # a zero vector stays zero
        for row in rows:
            row /= length
    out = np.empty((len(points), 3), dtype=np.float32)
    for r in range(3):
        out[:, r] = rows[r]
    return out


def _points_to_patient(
    verts: np.ndarray, affine: np.ndarray, steps: tuple[int, int, int], offset: np.ndarray
) -> np.ndarray:
    """Index-space vertices of the (sampled, padded) block to LPS mm, float32."""
    linear = affine[:3, :3] @ np.diag(np.asarray(steps, dtype=np.float64))
    return _map_rows(verts, linear, affine[:3, :3] @ offset + affine[:3, 3], False)


def _normals_to_patient(
    normals: np.ndarray, linear: np.ndarray, steps: tuple[int, int, int]
) -> np.ndarray:
    """Map index-space gradient normals to unit LPS normals (inverse transpose of the map)."""
    to_patient = linear @ np.diag(np.asarray(steps, dtype=np.float64))
    return _map_rows(normals, np.linalg.inv(to_patient).T, np.zeros(3), True)


def _use_both_cores() -> None:
    """Run VTK's SMP filters (flying edges among them) on every core.

    The PyPI wheels build the STDThread backend but start on "Sequential"; a user who chose
    a backend through ``VTK_SMP_BACKEND_IN_USE`` keeps it.
    """
    if "VTK_SMP_BACKEND_IN_USE" not in os.environ:
        smp = vtkSMPTools()
        if smp.GetBackend() == "Sequential":
            smp.SetBackend("STDThread")


def _flying_edges(
    block: np.ndarray, level: float, normals: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flying-edges isosurface of an (X, Y, Z) array in index coordinates.

    Returns vertices (N, 3) float32, outward-wound faces (F, 3) int32 and gradient normals
    (N, 3) float32 ((N, 0) when not ``normals``), all in index space; VTK computes the
    normals in parallel, cheaper than from faces.
    """
    _use_both_cores()
    fe = vtkFlyingEdges3D()
    fe.SetInputData(image_data(block))
    fe.SetValue(0, float(level))
    fe.SetComputeNormals(normals)
    fe.ComputeGradientsOff()
    fe.ComputeScalarsOff()
    fe.Update()
    out = fe.GetOutput()
    if out.GetNumberOfPoints() == 0:
        return (
            np.zeros((0, 3), np.float32),
            np.zeros((0, 3), np.int32),
            np.zeros((0, 3 if normals else 0), np.float32),
        )
    # copies, so that VTK's arrays (int64 connectivity: twice our faces) go with the filter
    verts = numpy_support.vtk_to_numpy(out.GetPoints().GetData()).astype(np.float32)
    conn = numpy_support.vtk_to_numpy(out.GetPolys().GetConnectivityArray())
    faces = conn.astype(np.int32).reshape(-1, 3)
    if normals:
        vectors = numpy_support.vtk_to_numpy(out.GetPointData().GetNormals()).astype(np.float32)
    else:
        vectors = np.zeros((len(verts), 0), np.float32)
    # VTK winds flying-edges triangles counter-clockwise seen from the lower values and
    # its normals point down the gradient: both outward for a structure above the level
    # (checked by the sphere and ellipsoid tests).
    return verts, faces, vectors
