"""The placed edge collapse (``decimate="placed"``): vertices moved to the quadric's point,
held everywhere (measured densely), the topology kept, fewer triangles than the half-edge
collapse at the same bound; and the check that measures a model whose vertices moved."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
from test_bounds import dense_max, miss_surface, scene
from test_collapse import BOUNDS, held_everywhere, random_surfaces
from test_schroeder import (
    assert_valid_mesh,
    boundary_edges,
    boundary_loop_count,
    euler_characteristic,
    icosphere,
)

from miss import Mesh, decimate
from miss.decimate.collapse import collapse
from miss.decimate.placed import COUNTS, native, placed
from miss.measure import bound_check


def assert_same_topology(before: Mesh, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Oriented and manifold, no vertex the input did not have (by index), the same Euler
    characteristic, closed where the input was, as many boundary loops otherwise."""
    assert_valid_mesh(vertices, before.faces, faces)
    assert euler_characteristic(faces) == euler_characteristic(before.faces)
    if len(boundary_edges(before.faces)) == 0:
        assert len(boundary_edges(faces)) == 0
    else:
        assert boundary_loop_count(faces) == boundary_loop_count(before.faces)


def test_the_kernel_is_built() -> None:
    assert native(), "src/miss/decimate/_placed.cpp was not built: run `make test` again"


@pytest.fixture(scope="module")
def bone(datasets) -> Mesh:
    return miss_surface(datasets)


@pytest.mark.slow  # the whole CThead bone, placed against the half-edge collapse
@pytest.mark.parametrize("bound", BOUNDS)
def test_cthead_bone_is_held_densely_with_fewer_triangles_than_the_half_edge_collapse(
    bone: Mesh, bound: float
) -> None:
    bound_mm = bound * bone.diagonal()
    counts = np.zeros(len(COUNTS), np.int64)
    vertices, faces, _ = placed(bone, 0.99, bound_mm, counts=counts)
    after = Mesh(vertices.astype(np.float32), faces)
    assert held_everywhere(bone, after, bound_mm, 200_000)
    assert_same_topology(bone, vertices, faces)
    assert counts[3] > counts[4] + counts[5]  # most collapses went to the quadric's point
    out, report = decimate(bone, "placed", reduce=0.99, error_bound=bound)
    assert report.finished_with == "placed" and report.bound_held
    assert report.max_error_mm <= report.bound_mm + 1e-6 * bone.diagonal()
    assert out.n_triangles == len(faces)
    half_edge, _ = collapse(bone, 0.99, bound_mm)
    # measured: 87 532 against 117 142 at 0.002 (0.75), 198 102 against 243 018 at 0.0005
    # (0.82); with one distance per triangle, not an error box, 0.85 and 0.90
    assert out.n_triangles < (0.80 if bound >= 0.002 else 0.85) * len(half_edge)


@random_surfaces
def test_random_surfaces_are_held_densely_and_keep_their_topology(
    kind: str, seed: int, noise: float, pieces: int, bound: float
) -> None:
    mesh = scene(kind, seed, noise, pieces)
    bound_mm = bound * mesh.diagonal()
    vertices, faces, _ = placed(mesh, 0.99, bound_mm)
    after = Mesh(vertices.astype(np.float32), faces)
    assert held_everywhere(mesh, after, bound_mm, 50_000)
    assert_same_topology(mesh, vertices, faces)


def test_it_moves_vertices_and_a_locked_one_neither_moves_nor_goes() -> None:
    mesh = scene("sphere", 0, 0.2, 0)
    locked = np.zeros(mesh.n_vertices, dtype=bool)
    locked[::7] = True
    vertices, faces, _ = placed(mesh, 0.99, 0.01 * mesh.diagonal(), locked)
    assert len(faces) < 0.5 * mesh.n_triangles
    assert np.isin(np.flatnonzero(locked), faces).all()
    assert (vertices[locked] == mesh.vertices[locked]).all()
    used = np.unique(faces)
    moved = (vertices[used] != mesh.vertices[used]).any(axis=1)
    assert moved.sum() > 0.2 * len(used)


def test_a_tetrahedron_stays() -> None:
    verts = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]], dtype=np.float32)
    faces = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]], dtype=np.int32)
    vertices, out, _ = placed(Mesh(verts, faces), 0.99, 100.0)
    assert sorted(map(sorted, out.tolist())) == sorted(map(sorted, faces.tolist()))
    assert (vertices == verts).all()


def test_a_box_with_flat_sides_loses_most_of_its_triangles_within_a_tiny_bound() -> None:
    # a collapse inside a flat side costs 0 mm wherever the vertex goes along it
    mesh = scene("box", 1, 0.0, 0)
    vertices, faces, _ = placed(mesh, 0.99, 1e-3)
    assert len(faces) < 0.2 * mesh.n_triangles
    after = Mesh(vertices.astype(np.float32), faces)
    assert dense_max(mesh, after, 20_000) <= 1e-3 + 1e-6 * mesh.diagonal()
    assert_same_topology(mesh, vertices, faces)


def test_each_vertex_is_keyed_at_its_cost_so_none_is_popped_too_soon() -> None:
    """A vertex's key is its cheapest edge's cost, kept exact as its neighbours collapse: no
    vertex is popped before its turn and put back (a key kept as the lower of the old one
    and the new edge's put back 361 733 of 750 120 on CThead bone at 0.002)."""
    mesh = scene("sphere", 3, 0.02, 0)
    counts = np.zeros(len(COUNTS), np.int64)
    vertices, faces, _ = placed(mesh, 0.99, 0.002 * mesh.diagonal(), counts=counts)
    assert len(faces) < 0.5 * mesh.n_triangles
    assert counts[0] > 0 and counts[1] == 0, dict(zip(COUNTS, counts.tolist(), strict=True))
    assert_same_topology(mesh, vertices, faces)


def test_the_check_measures_a_vertex_that_moved() -> None:
    """An output vertex that moved off the surface is out of bound by as much: the check
    measures it (and the input vertex it left). Measured as if it had not moved, the
    output would be the input, 0 mm."""
    v, f = icosphere(3)
    mesh = Mesh((50.0 * v).astype(np.float32), f.astype(np.int32))
    moved = mesh.vertices.copy()
    normal = moved[10] / np.linalg.norm(moved[10])
    moved[10] += 1.5 * normal
    check = bound_check(mesh, mesh.faces, vertices=moved)
    assert 1.4 < check.max_mm <= 1.5 + 1e-4
    assert (check.edges == 10).any()  # the moved vertex, among what was measured
    assert check.to_output[10] > 0.3  # the input vertex it left, to the output
    assert bound_check(mesh, mesh.faces, vertices=mesh.vertices.copy()).max_mm == 0.0


@pytest.mark.slow  # the whole CThead bone, twice
def test_the_slabs_give_the_same_model_on_one_thread_as_on_two(bone: Mesh, monkeypatch) -> None:
    module = importlib.import_module("miss.decimate.placed")  # the module, not the function
    bound_mm = 0.002 * bone.diagonal()
    monkeypatch.setattr(module, "usable_cores", lambda: 2)
    v2, f2, _ = placed(bone, 0.99, bound_mm)
    monkeypatch.setattr(module, "usable_cores", lambda: 1)
    v1, f1, _ = placed(bone, 0.99, bound_mm)
    assert module._slab_count(bone.n_triangles) > 1
    assert np.array_equal(f1, f2) and np.array_equal(v1, v2)
