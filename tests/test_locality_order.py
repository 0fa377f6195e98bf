"""``locality_order``: the layout every file of a job holds its scene in (issue 41)."""

from __future__ import annotations

import numpy as np
import pytest

from miss.geometry import locality_order, vertex_normals
from miss.types import Mesh


def _triangles(mesh: Mesh) -> np.ndarray:
    """Each triangle as its corners' coordinates, rows sorted: the surface, whatever the
    layout (a triangle keeps its winding: its corners are not turned)."""
    corners = mesh.vertices[mesh.faces].reshape(len(mesh.faces), 9)
    return corners[np.lexsort(corners.T[::-1])]


@pytest.fixture
def grid() -> Mesh:
    """A 60x60 grid of two triangles a square, its triangles shuffled, three unused
    vertices at the end."""
    n = 60
    y, x = np.mgrid[0:n, 0:n]
    vertices = np.c_[x.ravel(), y.ravel(), np.sin(x.ravel() / 7.0)].astype(np.float32)
    vertices = np.vstack([vertices, np.ones((3, 3), np.float32) * 99])
    corner = (y[:-1, :-1] * n + x[:-1, :-1]).ravel()
    faces = np.concatenate(
        [np.c_[corner, corner + 1, corner + n + 1], np.c_[corner, corner + n + 1, corner + n]]
    ).astype(np.int32)
    faces = faces[np.random.default_rng(4).permutation(len(faces))]
    return Mesh(vertices, faces, vertex_normals(vertices, faces))


def test_the_same_surface_laid_out_for_locality(grid: Mesh) -> None:
    ordered = locality_order(grid)
    assert ordered.n_triangles == grid.n_triangles
    assert ordered.n_vertices == grid.n_vertices - 3  # the unused ones are dropped
    assert ordered.faces.dtype == grid.faces.dtype
    assert ordered.vertices.dtype == grid.vertices.dtype
    np.testing.assert_array_equal(_triangles(ordered), _triangles(grid))
    # each vertex keeps its normal
    where = {tuple(v): i for i, v in enumerate(grid.vertices[:-3])}
    assert grid.normals is not None and ordered.normals is not None
    before = grid.normals[[where[tuple(v)] for v in ordered.vertices]]
    np.testing.assert_array_equal(ordered.normals, before)
    # vertices in first-use order, neighbours near: small steps between consecutive
    # triangles' first corners, where the shuffled mesh jumps across the grid
    steps = lambda m: np.median(np.abs(np.diff(m.faces[:, 0].astype(np.int64))))  # noqa: E731
    assert steps(ordered) * 20 < steps(grid), (steps(ordered), steps(grid))
    first_use = np.unique(ordered.faces.ravel(), return_index=True)[1]
    assert (np.diff(first_use) > 0).all()


def test_a_mesh_with_face_labels_is_kept_as_it_is(grid: Mesh) -> None:
    labelled = Mesh(grid.vertices, grid.faces, grid.normals, np.arange(grid.n_triangles) % 4)
    assert locality_order(labelled) is labelled
