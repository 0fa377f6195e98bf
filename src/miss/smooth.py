"""Windowed-sinc smoothing (Taubin 1995, VTK's vtkWindowedSincPolyDataFilter).

A low-pass filter on the mesh: stair steps and marching-cubes ripples go, shape
and volume stay (unlike Laplacian smoothing, which shrinks). Only points move;
the triangles stay the same, so surfaces sharing vertices keep sharing them.
"""

from __future__ import annotations

import numpy as np
from vtkmodules.util import numpy_support
from vtkmodules.vtkFiltersCore import vtkWindowedSincPolyDataFilter

from miss._vtk import to_polydata
from miss.geometry import enclosed_volume, vertex_normals
from miss.spec import PASSBAND, check_smoothing
from miss.types import Mesh

#: Relative volume change above which a part's smoothing is reported as not volume-preserving.
VOLUME_TOLERANCE = 0.02


def windowed_sinc(
    vertices: np.ndarray, faces: np.ndarray, iterations: int, passband: float = PASSBAND
) -> np.ndarray:
    """Smoothed vertex positions.

    Parameters
    ----------
    vertices : (N, 3) float array, mm
    faces : (F, 3) int array
    iterations : int
        Filter order; 10-30 removes voxel stair steps.
    passband : float
        In (0, 2); frequencies above it are damped. 0.1 keeps organ shapes.

    Returns
    -------
    (N, 3) float64 array, mm
        Open borders and non-manifold edges (where three labels meet) move only
        along themselves, so neighbouring surfaces stay joined.
    """
    check_smoothing(iterations, passband)
    if iterations == 0 or len(faces) == 0:
        return np.asarray(vertices, dtype=np.float64)
    sinc = vtkWindowedSincPolyDataFilter()
    sinc.SetInputData(to_polydata(vertices, faces))
    sinc.SetNumberOfIterations(int(iterations))
    sinc.SetPassBand(float(passband))
    # Normalising to a unit cube first makes the filter's stability independent of mm scale.
    sinc.NormalizeCoordinatesOn()
    sinc.BoundarySmoothingOff()  # cut borders (a region's edge) stay where the data put them
    sinc.FeatureEdgeSmoothingOff()
    sinc.NonManifoldSmoothingOn()
    sinc.Update()
    points = sinc.GetOutput().GetPoints().GetData()
    return numpy_support.vtk_to_numpy(points).astype(np.float64)


def smooth_mesh(mesh: Mesh, iterations: int, passband: float = PASSBAND) -> tuple[Mesh, float]:
    """Smooth one closed mesh; returns it and its relative volume change (0.01 = +1 %)."""
    if iterations == 0:
        check_smoothing(iterations, passband)
        return mesh, 0.0
    points = windowed_sinc(mesh.vertices, mesh.faces, iterations, passband)
    before = enclosed_volume(mesh.vertices, mesh.faces)
    after = enclosed_volume(points, mesh.faces)
    change = after / before - 1.0 if before else 0.0
    vertices = points.astype(np.float32)
    return Mesh(vertices, mesh.faces, vertex_normals(vertices, mesh.faces)), change


def displacement(before: Mesh, after: Mesh) -> tuple[float, float]:
    """How far smoothing moved a mesh: its vertices' largest and mean displacement, mm (the
    same vertices in the same order, as :func:`smooth_mesh` keeps them)."""
    if before.n_vertices == 0:
        return 0.0, 0.0
    moved = np.linalg.norm(
        after.vertices.astype(np.float64) - before.vertices.astype(np.float64), axis=1
    )
    return float(moved.max()), float(moved.mean())
