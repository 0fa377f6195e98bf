"""Isosurface extraction: marching cubes (VTK flying edges) in patient millimetres.

The surface is computed on the voxel index grid and mapped through the volume's
affine afterwards. Linear interpolation along cube edges commutes with affine maps,
so this is exact for sheared (gantry-tilted) and oblique grids alike.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import vtk
from vtk.util import numpy_support

from miss.errors import BadParameter, EmptySurface
from miss.types import Mesh, Volume

SampleRate = int | Sequence[int]
Roi = Sequence[int]  # (i0, i1, j0, j1, k0, k1), 0-based, inclusive


def _sample_steps(sample_rate: SampleRate) -> tuple[int, int, int]:
    steps = (sample_rate,) * 3 if np.isscalar(sample_rate) else tuple(sample_rate)
    if len(steps) != 3:
        raise BadParameter(f"sample rate needs one integer or three (x,y,z), got {sample_rate!r}.")
    if any(int(s) != s or s < 1 for s in steps):
        raise BadParameter(f"sample rate must be whole numbers >= 1, got {sample_rate!r}.")
    return int(steps[0]), int(steps[1]), int(steps[2])


def _region(
    dims: tuple[int, int, int], slices: tuple[int, int] | None, roi: Roi | None
) -> list[tuple[int, int]]:
    """0-based inclusive (start, stop) per axis after the slice range and ROI."""
    box = [(0, d - 1) for d in dims]
    if roi is not None:
        if len(roi) != 6:
            raise BadParameter("ROI needs six voxel indices: i0,i1,j0,j1,k0,k1.")
        box = [(int(roi[2 * a]), int(roi[2 * a + 1])) for a in range(3)]
    if slices is not None:
        start, end = slices
        if not 1 <= start <= end <= dims[2]:
            raise BadParameter(
                f"slice range {start}..{end} is outside 1..{dims[2]} (1-based, start <= end); "
                f"pick start and end slices within the volume's {dims[2]} slices."
            )
        k0, k1 = box[2]
        box[2] = (max(k0, start - 1), min(k1, end - 1))
    for axis, (lo, hi) in enumerate(box):
        if not 0 <= lo < hi <= dims[axis] - 1:
            raise BadParameter(
                f"region {lo}..{hi} on axis {'xyz'[axis]} is empty or outside 0..{dims[axis] - 1}; "
                "a surface needs at least two voxels along every axis."
            )
    return box


def _to_vtk_image(block: np.ndarray) -> vtk.vtkImageData:
    """Wrap an (X, Y, Z) array as vtkImageData with unit spacing (index space)."""
    flat = block.ravel(order="F")  # VTK wants x fastest: a view when block is F-ordered
    image = vtk.vtkImageData()
    image.SetDimensions(*block.shape)
    arr = numpy_support.numpy_to_vtk(flat, deep=False)
    image.GetPointData().SetScalars(arr)
    image._miss_keepalive = flat  # numpy_to_vtk(deep=False) does not own the memory
    return image


def polydata_to_arrays(poly: vtk.vtkPolyData) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (N,3) float64, faces (F,3) int32) of an all-triangle vtkPolyData."""
    if poly.GetNumberOfPoints() == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32)
    pts = numpy_support.vtk_to_numpy(poly.GetPoints().GetData()).astype(np.float64)
    polys = poly.GetPolys()
    conn = numpy_support.vtk_to_numpy(polys.GetConnectivityArray())
    return pts, conn.reshape(-1, 3).astype(np.int32)


def _pad_below(block: np.ndarray, level: float, span: float) -> np.ndarray:
    """Surround the block by one voxel far below the level so cut surfaces close (capped).

    The pad is very low so the cap's vertices, interpolated towards it, land within a
    few hundredths of a voxel of the last chosen slice rather than half a voxel beyond.
    """
    dtype = block.dtype
    if np.issubdtype(dtype, np.integer) and np.iinfo(dtype).min < level:
        low: float = float(np.iinfo(dtype).min)
    else:
        dtype = np.dtype(np.float32)
        low = level - 1e3 * max(span, 1.0)
    out = np.full(tuple(s + 2 for s in block.shape), low, dtype=dtype, order="F")
    out[1:-1, 1:-1, 1:-1] = block
    return out


def extract_surface(
    volume: Volume,
    level: float,
    sample_rate: SampleRate = 1,
    slices: tuple[int, int] | None = None,
    roi: Roi | None = None,
    *,
    closed: bool = True,
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

    Returns
    -------
    Mesh
        vertices (N, 3) float32 mm, faces (F, 3) int32 wound counter-clockwise seen
        from outside (from above-level towards below-level), outward unit normals.
    """
    if not np.isfinite(level):
        raise BadParameter(f"level must be a finite number, got {level!r}.")
    steps = _sample_steps(sample_rate)
    box = _region(volume.dims, slices, roi)
    block = volume.data[tuple(slice(lo, hi + 1, st) for (lo, hi), st in zip(box, steps, strict=True))]
    if min(block.shape) < 2:
        raise BadParameter(
            f"sample rate {steps} leaves {block.shape} voxels; a surface needs at least 2 per axis. "
            "Lower the sample rate or widen the slice range."
        )
    lo, hi = float(np.min(block)), float(np.max(block))
    if not lo < level < hi:
        raise EmptySurface(
            f"no surface at level {level:g}: the chosen region holds values {lo:g}..{hi:g}; "
            "pick a level inside that range."
        )
    offset = np.array([b[0] for b in box], dtype=np.float64)
    if closed:
        block = _pad_below(block, level, hi - lo)
        offset -= np.array(steps, dtype=np.float64)
    else:
        block = np.asfortranarray(block)
    verts, faces, index_normals = _flying_edges(block, level)
    if len(faces) == 0:
        raise EmptySurface(f"no surface at level {level:g} in the chosen region; pick another level.")
    ijk = verts * np.array(steps, dtype=np.float64) + offset
    xyz = ijk @ volume.affine[:3, :3].T + volume.affine[:3, 3]
    if np.linalg.det(volume.affine[:3, :3]) < 0:
        faces = faces[:, ::-1].copy()  # a mirroring affine flips the winding
    return Mesh(
        vertices=xyz.astype(np.float32),
        faces=faces,
        normals=_normals_to_patient(index_normals, volume.affine[:3, :3], steps),
    )


def _normals_to_patient(normals: np.ndarray, linear: np.ndarray, steps: tuple[int, int, int]) -> np.ndarray:
    """Map index-space gradient normals to unit LPS normals (inverse transpose of the map)."""
    to_patient = linear @ np.diag(np.asarray(steps, dtype=np.float64))
    out = normals.astype(np.float64) @ np.linalg.inv(to_patient)
    length = np.linalg.norm(out, axis=1, keepdims=True)
    np.divide(out, length, out=out, where=length > 0)
    return out.astype(np.float32)


def _flying_edges(block: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flying-edges isosurface of an (X, Y, Z) array in index coordinates.

    Returns vertices (N, 3), outward-wound faces (F, 3) and gradient normals (N, 3),
    all in index space; VTK computes the normals in parallel, cheaper than from faces.
    """
    fe = vtk.vtkFlyingEdges3D()
    fe.SetInputData(_to_vtk_image(block))
    fe.SetValue(0, float(level))
    fe.ComputeNormalsOn()
    fe.ComputeGradientsOff()
    fe.ComputeScalarsOff()
    fe.Update()
    out = fe.GetOutput()
    verts, faces = polydata_to_arrays(out)
    normals = numpy_support.vtk_to_numpy(out.GetPointData().GetNormals()) if len(faces) else verts
    # VTK winds flying-edges triangles counter-clockwise seen from the lower values and
    # its normals point down the gradient: both outward for a structure above the level
    # (checked by the sphere and ellipsoid tests).
    return verts, faces, normals
