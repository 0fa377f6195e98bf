"""numpy <-> VTK, in one place: polydata from triangle arrays and back, image data that
wraps a voxel array without a copy."""

from __future__ import annotations

import numpy as np
from vtkmodules.util import numpy_support
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkImageData, vtkPolyData

# VTK's own modules, not ``import vtk``: that loads every one of them (rendering, web,
# IO ...), a second of a command's start, for the three classes used here.


def to_polydata(vertices: np.ndarray, faces: np.ndarray) -> vtkPolyData:
    """vtkPolyData of a triangle mesh (deep copies, safe to keep)."""
    pts = vtkPoints()
    pts.SetData(
        numpy_support.numpy_to_vtk(np.ascontiguousarray(vertices, dtype=np.float64), deep=True)
    )
    offsets = np.arange(0, 3 * len(faces) + 1, 3, dtype=np.int64)
    cells = vtkCellArray()
    cells.SetData(
        numpy_support.numpy_to_vtkIdTypeArray(offsets, deep=True),
        numpy_support.numpy_to_vtkIdTypeArray(
            np.ascontiguousarray(faces, dtype=np.int64).ravel(), deep=True
        ),
    )
    poly = vtkPolyData()
    poly.SetPoints(pts)
    poly.SetPolys(cells)
    return poly


def image_data(block: np.ndarray) -> vtkImageData:
    """Wrap an (X, Y, Z) array as vtkImageData with unit spacing (index space)."""
    flat = block.ravel(order="F")  # VTK wants x fastest: a view when block is F-ordered
    image = vtkImageData()
    image.SetDimensions(*block.shape)
    arr = numpy_support.numpy_to_vtk(flat, deep=False)
    image.GetPointData().SetScalars(arr)
    # numpy_to_vtk(deep=False) does not own the memory; a VTK object takes Python
    # attributes, which its stubs don't know
    image._miss_keepalive = flat  # type: ignore[attr-defined]
    return image


def polydata_to_arrays(poly: vtkPolyData) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (N,3) float64, faces (F,3) int32) of an all-triangle vtkPolyData."""
    if poly.GetNumberOfPoints() == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32)
    pts = numpy_support.vtk_to_numpy(poly.GetPoints().GetData()).astype(np.float64)
    polys = poly.GetPolys()
    conn = numpy_support.vtk_to_numpy(polys.GetConnectivityArray())
    return pts, conn.reshape(-1, 3).astype(np.int32)
