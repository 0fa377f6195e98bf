"""Measured distance between two surfaces, in millimetres.

Used to report what a decimation really did, not just the bound it was given:
points are sampled on each surface (its vertices plus random points inside its
triangles) and their exact distance to the other surface is taken with VTK's
point-to-triangle distance (``vtkImplicitPolyDataDistance``), both ways.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import vtk
from vtk.util import numpy_support

from miss.types import Mesh


@dataclass(frozen=True)
class Deviation:
    """Two-sided distance between surfaces A and B, mm."""

    max_mm: float
    mean_mm: float
    samples: int


def to_polydata(vertices: np.ndarray, faces: np.ndarray) -> vtk.vtkPolyData:
    """vtkPolyData of a triangle mesh (deep copies, safe to keep)."""
    pts = vtk.vtkPoints()
    pts.SetData(numpy_support.numpy_to_vtk(np.ascontiguousarray(vertices, dtype=np.float64), deep=True))
    offsets = np.arange(0, 3 * len(faces) + 1, 3, dtype=np.int64)
    cells = vtk.vtkCellArray()
    cells.SetData(
        numpy_support.numpy_to_vtkIdTypeArray(offsets, deep=True),
        numpy_support.numpy_to_vtkIdTypeArray(np.ascontiguousarray(faces, dtype=np.int64).ravel(), deep=True),
    )
    poly = vtk.vtkPolyData()
    poly.SetPoints(pts)
    poly.SetPolys(cells)
    return poly


def sample_surface(mesh: Mesh, count: int, rng: np.random.Generator) -> np.ndarray:
    """(count, 3) points: all vertices used by faces (subsampled if too many) plus area-weighted
    random points inside triangles, so both corners and flat interiors are checked."""
    v = mesh.vertices.astype(np.float64)
    used = np.unique(mesh.faces)
    corners = v[rng.choice(used, size=min(len(used), count // 2), replace=False)]
    tri = v[mesh.faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    n_inner = count - len(corners)
    pick = rng.choice(len(tri), size=n_inner, p=area / area.sum())
    r1, r2 = rng.random(n_inner), rng.random(n_inner)
    flip = r1 + r2 > 1
    r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
    t = tri[pick]
    inner = t[:, 0] + r1[:, None] * (t[:, 1] - t[:, 0]) + r2[:, None] * (t[:, 2] - t[:, 0])
    return np.concatenate([corners, inner])


def distances_to(points: np.ndarray, mesh: Mesh) -> np.ndarray:
    """Unsigned distance in mm from each of (P, 3) points to the surface of ``mesh``."""
    implicit = vtk.vtkImplicitPolyDataDistance()
    implicit.SetInput(to_polydata(mesh.vertices, mesh.faces))
    src = numpy_support.numpy_to_vtk(np.ascontiguousarray(points, dtype=np.float64), deep=True)
    out = vtk.vtkDoubleArray()
    implicit.FunctionValue(src, out)
    return np.abs(numpy_support.vtk_to_numpy(out))


def deviation(a: Mesh, b: Mesh, samples: int = 100_000, seed: int = 0) -> Deviation:
    """Two-sided (symmetric Hausdorff-style) deviation between surfaces ``a`` and ``b``."""
    if a.n_triangles == 0 or b.n_triangles == 0:
        return Deviation(0.0, 0.0, 0)
    rng = np.random.default_rng(seed)
    d_ab = distances_to(sample_surface(a, samples, rng), b)
    d_ba = distances_to(sample_surface(b, samples, rng), a)
    both = np.concatenate([d_ab, d_ba])
    return Deviation(max_mm=float(both.max()), mean_mm=float(both.mean()), samples=len(both))
