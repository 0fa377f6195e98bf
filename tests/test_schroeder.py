"""Schroeder vertex decimation: topology, orientation, analytic shapes and the CThead scan."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from miss.decimate._schroeder import schroeder_decimate
from miss.geometry import boundary_edge_count, enclosed_volume, surface_area

# ----------------------------------------------------------------------------- test meshes


def icosphere(level: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere: icosahedron split `level` times, (V, 3) float64 and (F, 3) int32, CCW out."""
    t = (1 + 5**0.5) / 2
    v = np.array(
        [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t]]
        + [[0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
        dtype=np.float64,
    )
    f = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4]]
        + [[11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8]]
        + [[3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    )
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(level):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        mid = v[unique[:, 0]] + v[unique[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        ab, bc, ca = inverse.reshape(3, -1) + len(v)
        a, b, c = f.T
        f = np.concatenate(
            [np.stack(t, axis=1) for t in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))]
        )
        v = np.concatenate([v, mid])
    return v, f.astype(np.int32)


def grid_faces(n: int) -> np.ndarray:
    """Two CCW (seen from +z) triangles per cell of an n x n vertex grid numbered row by row."""
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="xy")
    a = (j * n + i).ravel()
    return np.concatenate([np.stack([a, a + 1, a + n + 1], 1), np.stack([a, a + n + 1, a + n], 1)])


def height_field(n: int, size: float = 10.0, bump: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Square [0, size]^2 in mm with a Gaussian bump of height `bump` mm in the middle."""
    x, y = np.meshgrid(np.linspace(0, size, n), np.linspace(0, size, n), indexing="xy")
    z = bump * np.exp(-((x - size / 2) ** 2 + (y - size / 2) ** 2) / (size / 6) ** 2)
    return np.stack([x.ravel(), y.ravel(), z.ravel()], 1), grid_faces(n).astype(np.int32)


def cube(n: int, size: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Closed cube surface centred on 0, each side an n x n grid, welded, CCW outward."""
    g = np.linspace(-size / 2, size / 2, n)
    u, w = (c.ravel() for c in np.meshgrid(g, g, indexing="xy"))
    quads = grid_faces(n)
    verts, faces = [], []
    for axis in range(3):
        others = [k for k in range(3) if k != axis]
        for sign in (-1.0, 1.0):
            p = np.zeros((n * n, 3))
            p[:, axis], p[:, others[0]], p[:, others[1]] = sign * size / 2, u, w
            # grid_faces winds about others[0] x others[1], which is +axis iff that order is cyclic
            outward = (sign > 0) == ((axis + 1) % 3 == others[0])
            faces.append((quads if outward else quads[:, ::-1]) + len(verts) * n * n)
            verts.append(p)
    v, inverse = np.unique(np.round(np.concatenate(verts), 9), axis=0, return_inverse=True)
    return v, inverse.ravel()[np.concatenate(faces)].astype(np.int32)


# ----------------------------------------------------------------------------- invariants


def edge_keys(faces: np.ndarray, directed: bool = False) -> np.ndarray:
    """One int64 per triangle side (3F); undirected keys ignore the side's direction."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    if not directed:
        e.sort(axis=1)
    return e[:, 0] * (int(faces.max()) + 1) + e[:, 1]


def face_keys(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """One int64 per triangle, independent of corner order."""
    s = np.sort(faces, axis=1).astype(np.int64)
    return (s[:, 0] * n_vertices + s[:, 1]) * n_vertices + s[:, 2]


def boundary_edges(faces: np.ndarray) -> np.ndarray:
    """(B, 2) vertex pairs of the edges used by one triangle only."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, first, counts = np.unique(edge_keys(faces), return_index=True, return_counts=True)
    return e[first[counts == 1]]


def euler_characteristic(faces: np.ndarray) -> int:
    return len(np.unique(faces)) - len(np.unique(edge_keys(faces))) + len(faces)


def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def assert_valid_mesh(vertices: np.ndarray, faces: np.ndarray, new: np.ndarray) -> None:
    """Indices valid, no vertex created, no degenerate or duplicate triangle, every directed
    edge used once (consistent orientation, at most two triangles per edge)."""
    assert new.dtype == np.int32 and new.ndim == 2 and new.shape[1] == 3
    assert new.min() >= 0 and new.max() < len(vertices)
    assert np.isin(new, faces).all(), "a vertex the input never used appears"
    assert not (
        (new[:, 0] == new[:, 1]) | (new[:, 1] == new[:, 2]) | (new[:, 2] == new[:, 0])
    ).any()
    assert len(np.unique(face_keys(new, len(vertices)))) == len(new), "duplicate triangles"
    directed = edge_keys(new, directed=True)
    assert len(np.unique(directed)) == len(directed), (
        "inconsistent orientation or non-manifold edge"
    )
    # Marching cubes can emit zero-area triangles (coincident vertices); none may be new.
    flat = new[triangle_areas(vertices, new) == 0]
    assert np.isin(face_keys(flat, len(vertices)), face_keys(faces, len(vertices))).all()


def boundary_loop_count(faces: np.ndarray) -> int:
    b = boundary_edges(faces)
    if len(b) == 0:
        return 0
    ids, local = np.unique(b, return_inverse=True)
    local = local.reshape(-1, 2)
    graph = coo_matrix((np.ones(len(b)), (local[:, 0], local[:, 1])), shape=(len(ids), len(ids)))
    return connected_components(graph, directed=False)[0]


# ----------------------------------------------------------------------------- analytic shapes


def test_ellipsoid_keeps_closed_topology_orientation_and_volume():
    unit, faces = icosphere(4)
    vertices = unit * [30.0, 20.0, 10.0]
    before_v, before_f = vertices.copy(), faces.copy()
    new, info = schroeder_decimate(vertices, faces, reduce=0.8, error_bound=0.05, max_error=1.0)
    assert info["reduction"] >= 0.8
    assert len(new) <= 0.2 * len(faces)
    assert boundary_edge_count(new) == 0
    assert euler_characteristic(new) == euler_characteristic(faces) == 2
    assert_valid_mesh(vertices, faces, new)
    np.testing.assert_array_equal(vertices, before_v)  # inputs untouched
    np.testing.assert_array_equal(faces, before_f)
    exact = 4 / 3 * np.pi * 30 * 20 * 10
    assert 0 < enclosed_volume(vertices, new) <= enclosed_volume(vertices, faces) < exact
    assert enclosed_volume(vertices, new) == pytest.approx(exact, rel=0.03)
    assert info["removed_vertices"] == len(vertices) - len(np.unique(new))


def test_flat_square_goes_to_two_triangles_with_zero_error():
    vertices, faces = height_field(21)
    new, info = schroeder_decimate(vertices, faces, reduce=0.999, error_bound=0.0)
    assert_valid_mesh(vertices, faces, new)
    assert len(new) == 2
    corners = {(0.0, 0.0), (10.0, 0.0), (0.0, 10.0), (10.0, 10.0)}
    assert {tuple(p) for p in vertices[np.unique(new), :2]} == corners
    assert surface_area(vertices, new) == pytest.approx(100.0, rel=1e-12)
    assert info["final_bound_mm"] == 0.0


def test_open_bump_keeps_one_boundary_and_drops_straight_boundary_vertices():
    vertices, faces = height_field(31, bump=2.0)
    new, info = schroeder_decimate(
        vertices, faces, reduce=0.98, error_bound=0.05, max_error=0.5, accumulate=False
    )
    assert info["reduction"] >= 0.98
    assert_valid_mesh(vertices, faces, new)
    assert boundary_loop_count(new) == boundary_loop_count(faces) == 1
    assert euler_characteristic(new) == euler_characteristic(faces) == 1
    # The straight sides are lines: only the four corners may stay on them.
    assert boundary_edge_count(faces) == 120
    assert boundary_edge_count(new) == 4


def test_cube_keeps_corners_and_volume():
    vertices, faces = cube(11)
    new, info = schroeder_decimate(vertices, faces, reduce=0.99, error_bound=0.0)
    assert_valid_mesh(vertices, faces, new)
    kept = vertices[np.unique(new)]
    corners = (np.abs(vertices) == 1.0).all(axis=1)
    assert corners.sum() == 8
    assert {tuple(p) for p in kept} == {tuple(p) for p in vertices[corners]}
    assert len(new) == 12
    assert enclosed_volume(vertices, new) == pytest.approx(8.0, rel=1e-12)
    assert euler_characteristic(new) == 2 and boundary_edge_count(new) == 0


def test_closed_surfaces_stop_at_a_tetrahedron():
    tetra = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int32)
    # A feature angle of 180 degrees turns creases off, so only topology can stop a deletion.
    new, info = schroeder_decimate(tetra, faces, reduce=0.9, error_bound=10.0, feature_angle=180.0)
    assert len(new) == 4 and info["removed_vertices"] == 0
    vertices, faces = icosphere(1)
    new, _ = schroeder_decimate(vertices, faces, reduce=0.99, error_bound=10.0, feature_angle=180.0)
    assert_valid_mesh(vertices, faces, new)
    assert len(new) >= 4 and euler_characteristic(new) == 2 and boundary_edge_count(new) == 0


def test_small_hole_stays_open():
    # Each vertex on a 3-edge hole has its chord already as a boundary edge; using it would
    # close the hole.
    vertices, faces = icosphere(2)
    faces = faces[1:]
    new, _ = schroeder_decimate(vertices, faces, reduce=0.99, error_bound=10.0, feature_angle=180.0)
    assert_valid_mesh(vertices, faces, new)
    assert boundary_loop_count(new) == 1 and boundary_edge_count(new) == 3
    assert euler_characteristic(new) == 1


def test_isolated_triangle_survives():
    vertices, faces = height_field(5)
    vertices = np.concatenate([vertices, [[20.0, 0.0, 0.0], [21.0, 0.0, 0.0], [20.0, 1.0, 0.0]]])
    faces = np.concatenate([faces, [[25, 26, 27]]]).astype(np.int32)
    new, _ = schroeder_decimate(vertices, faces, reduce=0.99, error_bound=100.0)
    assert_valid_mesh(vertices, faces, new)
    assert [25, 26, 27] in new.tolist()
    assert len(new) >= 2  # with a 100 mm bound the square may go down to one triangle


def test_deletion_that_would_flip_a_triangle_is_refused():
    # Deleting boundary vertex 0 would leave the triangle (1, 2, 3), wound clockwise.
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0.2, 0.1, 0], [-1, 0.5, 0]], dtype=np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
    new, _ = schroeder_decimate(vertices, faces, reduce=0.9, error_bound=1.0)
    a, b, c = (vertices[new[:, k]] for k in range(3))
    assert len(new) >= 1 and (np.cross(b - a, c - a)[:, 2] > 0).all()


def test_feature_angle_controls_crease_vertices():
    # With a feature angle above 90 degrees the cube's edges are not creases, so edge vertices
    # are simple with a large plane distance and, at bound 0, all stay.
    vertices, faces = cube(5)
    new, _ = schroeder_decimate(vertices, faces, reduce=0.99, error_bound=0.0, feature_angle=120.0)
    on_edges = (np.abs(vertices) == 1.0).sum(axis=1) >= 2
    assert set(np.flatnonzero(on_edges)) <= set(np.unique(new))


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    roughness=st.floats(0.0, 0.2),
    reduce=st.floats(0.3, 0.95),
    bound=st.floats(0.0, 0.05),
)
def test_random_bumpy_spheres_stay_closed_and_oriented(seed, roughness, reduce, bound):
    unit, faces = icosphere(3)
    radius = 1.0 + roughness * np.random.default_rng(seed).random(len(unit))
    vertices = unit * radius[:, None]
    new, info = schroeder_decimate(vertices, faces, reduce=reduce, error_bound=bound, max_error=0.5)
    assert_closed_sphere(vertices, faces, new, info)


def assert_closed_sphere(vertices, faces, new, info) -> None:
    """A decimated sphere: valid, closed, genus 0, outward, its reduction as reported."""
    assert_valid_mesh(vertices, faces, new)
    assert boundary_edge_count(new) == 0
    assert euler_characteristic(new) == 2
    assert enclosed_volume(vertices, new) > 0
    assert 0.0 <= info["reduction"] == 1 - len(new) / len(faces)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), reduce=st.floats(0.3, 0.99), bound=st.floats(0.0, 0.5))
def test_random_height_fields_keep_their_boundary(seed, reduce, bound):
    vertices, faces = height_field(15)
    vertices[:, 2] = np.random.default_rng(seed).random(len(vertices))
    new, _ = schroeder_decimate(vertices, faces, reduce=reduce, error_bound=bound, max_error=2.0)
    assert_valid_mesh(vertices, faces, new)
    assert boundary_loop_count(new) == 1
    assert euler_characteristic(new) == 1


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), passes=st.integers(1, 6), bound=st.floats(0.001, 0.02))
def test_paper_schedule_runs_whole_passes_at_rising_bounds(seed, passes, bound):
    # vtkDecimate's iterations: pass k at k x bound, each pass to its end, at most N passes
    # (the paper's local criterion: accumulated error would keep a noisy sphere whole)
    unit, faces = icosphere(3)
    vertices = unit * (1.0 + 0.1 * np.random.default_rng(seed).random(len(unit)))[:, None]
    one, info_one = schroeder_decimate(
        vertices, faces, reduce=0.9, error_bound=bound, paper_passes=1, accumulate=False
    )
    new, info = schroeder_decimate(
        vertices, faces, reduce=0.9, error_bound=bound, paper_passes=passes, accumulate=False
    )
    assert_valid_mesh(vertices, faces, new)
    assert euler_characteristic(new) == 2
    assert 1 <= info["passes"] <= passes
    assert info["final_bound_mm"] == pytest.approx(info["passes"] * bound)
    # stopping only between passes: the first pass removes all it can at the bound, so more
    # passes remove at least as much, and a run that ends early has met the target
    assert info_one["passes"] == 1 and len(new) <= len(one)
    if info["passes"] < passes:
        assert info["reduction"] >= 0.9
    strict, _ = schroeder_decimate(
        vertices, faces, reduce=0.999, error_bound=bound, max_error=bound, accumulate=False
    )
    assert len(strict) <= len(one) < len(faces)  # strict mode repeats passes at the bound


def test_paper_schedule_is_for_the_papers_decimation_only():
    from miss.decimate import decimate
    from miss.errors import BadParameter
    from miss.types import Mesh

    vertices, faces = icosphere(2)
    with pytest.raises(BadParameter, match="schroeder"):
        decimate(Mesh(vertices.astype(np.float32), faces), "quadric", paper_passes=6)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"reduce": 1.0, "error_bound": 0.1}, "reduce"),
        ({"reduce": 0.5, "error_bound": -1.0}, "error_bound"),
        ({"reduce": 0.5, "error_bound": 0.1, "max_error": float("nan")}, "max_error"),
    ],
)
def test_bad_parameters_are_rejected(kwargs, message):
    vertices, faces = icosphere(1)
    with pytest.raises(ValueError, match=message):
        schroeder_decimate(vertices, faces, **kwargs)


def test_bad_faces_are_rejected():
    vertices, faces = icosphere(1)
    with pytest.raises(ValueError, match="out of range"):
        schroeder_decimate(vertices, faces + len(vertices), reduce=0.5, error_bound=0.1)
    faces[0, 1] = faces[0, 0]
    with pytest.raises(ValueError, match="repeat a vertex"):
        schroeder_decimate(vertices, faces, reduce=0.5, error_bound=0.1)


# ----------------------------------------------------------------------------- slabs


def bumpy_sphere(seed: int, level: int = 5, roughness: float = 0.05):
    unit, faces = icosphere(level)
    radius = 1.0 + roughness * np.random.default_rng(seed).random(len(unit))
    return unit * radius[:, None], faces


@pytest.mark.parametrize("count", [2, 3, 4, 8])
def test_slabs_share_no_neighbour(count):
    # what lets slabs be decimated side by side: a slab's vertices have neighbours in their
    # own slab only (its own vertices or the guard's), so no two slabs share a neighbour
    from miss.decimate._fan import domains as _domains
    from miss.decimate._fan import slabs as _slabs

    vertices, faces = bumpy_sphere(0)
    slab = _slabs(vertices, faces, count)
    alive = np.ones(len(faces), dtype=bool)
    degree = np.bincount(faces.ravel(), minlength=len(vertices)).astype(np.int32)
    order, starts = _domains(faces, alive, degree, slab, count)
    assert sorted(order.tolist()) == list(range(len(vertices)))  # each vertex once
    owner = np.full(len(vertices), -1)
    for d in range(count):
        owner[order[starts[d] : starts[d + 1]]] = d
    guard = order[starts[count] :]
    assert len(guard) < 0.05 * (count - 1) * len(vertices) and all(
        starts[d + 1] > starts[d] for d in range(count)
    )
    near = np.full(len(vertices), -1)  # the slab whose vertex each vertex neighbours
    for a, b in np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]):
        for u, w in ((a, b), (b, a)):
            if owner[u] >= 0:
                assert owner[w] in (owner[u], -1) and slab[w] == owner[u]
                assert near[w] in (-1, owner[u]), "two slabs share a neighbour"
                near[w] = owner[u]


def test_slabs_give_the_same_output_on_any_number_of_cores(monkeypatch):
    # the slabs are set by the mesh, not the machine: one core or many, the same triangles;
    # and the run keeps what the serial run keeps (closed, oriented, within the bound)
    from miss import Mesh
    from miss.decimate import _schroeder as kernel
    from miss.measure._jit import bound_check

    vertices, faces = bumpy_sphere(1)
    serial, _ = schroeder_decimate(vertices, faces, reduce=0.9, error_bound=0.002, max_error=0.02)
    monkeypatch.setattr(kernel, "_SLAB_FACES", 2_000)  # 20 480 triangles: 4 slabs
    assert kernel._slab_count(len(faces), 0) == 4
    runs = []
    for cores in (1, 2, 4):
        monkeypatch.setattr(kernel.os, "cpu_count", lambda cores=cores: cores)
        runs.append(
            schroeder_decimate(vertices, faces, reduce=0.9, error_bound=0.002, max_error=0.02)
        )
    new, info = runs[0]
    for other, other_info in runs[1:]:
        assert np.array_equal(other, new) and other_info == info
    assert not np.array_equal(new, serial)  # the slabs did run
    assert_valid_mesh(vertices, faces, new)
    assert boundary_edge_count(new) == 0 and euler_characteristic(new) == 2
    assert abs(len(new) - len(serial)) <= 0.02 * len(serial)
    check = bound_check(Mesh(vertices.astype(np.float32), faces), new)
    assert check.max_mm <= info["final_bound_mm"] * 1.5  # accumulated error, checked by decimate


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    roughness=st.floats(0.0, 0.2),
    reduce=st.floats(0.3, 0.99),
    bound=st.floats(0.0, 0.05),
    count=st.sampled_from([2, 4]),
)
def test_random_bumpy_spheres_in_slabs_stay_closed_and_oriented(
    seed, roughness, reduce, bound, count
):
    from miss.decimate import _schroeder as kernel

    vertices, faces = bumpy_sphere(seed, level=4, roughness=roughness)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(kernel, "_SLAB_FACES", len(faces) // count)
        assert kernel._slab_count(len(faces), 0) == count
        new, info = schroeder_decimate(
            vertices, faces, reduce=reduce, error_bound=bound, max_error=0.5
        )
    assert_closed_sphere(vertices, faces, new, info)


# ----------------------------------------------------------------------------- CThead bone


def cthead_bone(folder) -> tuple[np.ndarray, np.ndarray]:
    """Flying-edges surface of CThead at level 1500 (bone), spacing (1, 1, 2) mm."""
    import vtk
    from vtk.util import numpy_support

    slices = [np.fromfile(folder / f"CThead.{i}", ">i2").reshape(256, 256) for i in range(1, 114)]
    volume = np.concatenate(slices).astype(np.int16).reshape(113, 256, 256)  # native order
    image = vtk.vtkImageData()
    image.SetDimensions(256, 256, 113)
    image.SetSpacing(1, 1, 2)
    image.GetPointData().SetScalars(numpy_support.numpy_to_vtk(volume.ravel(), deep=True))
    surface = vtk.vtkFlyingEdges3D()
    surface.SetInputData(image)
    surface.SetValue(0, 1500)
    surface.ComputeNormalsOff()
    surface.Update()
    out = surface.GetOutput()
    vertices = numpy_support.vtk_to_numpy(out.GetPoints().GetData()).astype(np.float64)
    faces = numpy_support.vtk_to_numpy(out.GetPolys().GetConnectivityArray()).reshape(-1, 3)
    return vertices, faces.astype(np.int32)


def polydata(vertices: np.ndarray, faces: np.ndarray):
    import vtk
    from vtk.util import numpy_support

    points = vtk.vtkPoints()
    points.SetData(numpy_support.numpy_to_vtk(np.ascontiguousarray(vertices), deep=True))
    cells = vtk.vtkCellArray()
    ids = numpy_support.numpy_to_vtk(
        faces.ravel().astype(np.int64), deep=True, array_type=vtk.VTK_ID_TYPE
    )
    cells.SetData(3, ids)
    mesh = vtk.vtkPolyData()
    mesh.SetPoints(points)
    mesh.SetPolys(cells)
    return mesh


def sample_surface(vertices, faces, n, rng) -> np.ndarray:
    """n points uniformly distributed by area on the triangles, (n, 3) mm."""
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    area = triangle_areas(vertices, faces)
    pick = rng.choice(len(faces), n, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(n))[:, None], rng.random(n)[:, None]
    return (1 - r1) * a[pick] + r1 * (1 - r2) * b[pick] + r1 * r2 * c[pick]


def distances(vertices, faces, points) -> np.ndarray:
    """Unsigned distance (mm) of points to a surface, vtkImplicitPolyDataDistance vectorised."""
    import vtk
    from vtk.util import numpy_support

    implicit = vtk.vtkImplicitPolyDataDistance()
    implicit.SetInput(polydata(vertices, faces))
    out = vtk.vtkDoubleArray()
    implicit.FunctionValue(numpy_support.numpy_to_vtk(np.ascontiguousarray(points), deep=True), out)
    return np.abs(numpy_support.vtk_to_numpy(out))


def deviation(v0, f0, v1, f1, n=100_000) -> np.ndarray:
    """Two-sided sampled distances (mm) between two surfaces."""
    rng = np.random.default_rng(0)
    there = distances(v1, f1, sample_surface(v0, f0, n, rng))
    back = distances(v0, f0, sample_surface(v1, f1, n, rng))
    return np.concatenate([there, back])


@pytest.fixture(scope="module")
def cthead_surface(datasets):
    return cthead_bone(datasets / "ct_head_stanford_cthead")


@pytest.fixture(scope="module")
def cthead(cthead_surface):
    """The paper's local criterion (no accumulated error), the bound raised to 10x."""
    vertices, faces = cthead_surface
    diagonal = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    new, info = schroeder_decimate(
        vertices, faces, reduce=0.9, error_bound=0.0002 * diagonal, accumulate=False
    )
    return vertices, faces, new, info, deviation(vertices, faces, vertices, new)


@pytest.fixture(scope="module")
def cthead_held(cthead_surface):
    """The same job through ``miss.decimate`` with the paper's schedule: accumulated error,
    and the result checked and held within the bound it ended at."""
    from miss import Mesh, decimate

    vertices, faces = cthead_surface
    out, report = decimate(Mesh(vertices, faces), "schroeder", 0.9, 0.0002, schedule="paper")
    info = {"final_bound_mm": report.final_bound_mm}
    return out, report, info, deviation(vertices, faces, out.vertices, out.faces)


def component_labels(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    a = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    b = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(n_vertices, n_vertices))
    return connected_components(graph, directed=False)[1]


def closed_components(faces: np.ndarray, labels: np.ndarray) -> set[int]:
    return set(labels[faces[:, 0]].tolist()) - set(labels[boundary_edges(faces)[:, 0]].tolist())


@pytest.mark.slow
def test_cthead_bone_reaches_85_percent(cthead):
    vertices, faces, new, info, _ = cthead
    assert len(faces) > 500_000
    assert info["reduction"] >= 0.85


def test_cthead_bone_keeps_topology(cthead):
    vertices, faces, new, info, _ = cthead
    assert_valid_mesh(vertices, faces, new)
    labels = component_labels(faces, len(vertices))  # decimation never joins or splits parts
    assert set(labels[new[:, 0]].tolist()) == set(labels[faces[:, 0]].tolist())
    assert closed_components(new, labels) == closed_components(faces, labels)
    assert boundary_loop_count(new) == boundary_loop_count(faces)
    assert euler_characteristic(new) == euler_characteristic(faces)


def test_cthead_bone_mean_deviation_within_final_bound(cthead):
    # Each deletion is judged against the current, already decimated surface, so deviations
    # stack where deletions chain; on average the surface stays within one bound.
    *_, info, dist = cthead
    assert dist.mean() <= info["final_bound_mm"]


@pytest.mark.slow
def test_cthead_bone_max_deviation_like_decimatepro(cthead):
    # vtkDecimatePro judges vertices by the same local distance, so with its maximum error
    # set to our final bound it should stack up about as much error at the same reduction.
    import vtk
    from vtk.util import numpy_support

    vertices, faces, new, info, dist = cthead
    diagonal = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    pro = vtk.vtkDecimatePro()
    pro.SetInputData(polydata(vertices, faces))
    pro.SetTargetReduction(0.9)
    pro.PreserveTopologyOn()
    pro.SplittingOff()
    pro.BoundaryVertexDeletionOn()
    pro.SetFeatureAngle(75)
    pro.SetMaximumError(info["final_bound_mm"] / diagonal)
    pro.Update()
    out = pro.GetOutput()
    pro_vertices = numpy_support.vtk_to_numpy(out.GetPoints().GetData()).astype(np.float64)
    pro_faces = numpy_support.vtk_to_numpy(out.GetPolys().GetConnectivityArray()).reshape(-1, 3)
    pro_dist = deviation(vertices, faces, pro_vertices, pro_faces)
    assert len(new) <= 1.05 * len(pro_faces)
    assert dist.max() <= 1.5 * pro_dist.max()


@pytest.mark.slow
def test_cthead_bone_max_deviation_within_final_bound(cthead_held):
    # each triangle carries the error already spent on it (accumulated error) and the result
    # is checked, so deviations no longer stack up past the bound over chained deletions;
    # measured here by this file's own sampling, independently of the decimation's check
    out, report, info, dist = cthead_held
    assert report.bound_held and report.max_error_mm <= info["final_bound_mm"]
    assert dist.max() <= info["final_bound_mm"]
