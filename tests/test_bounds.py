"""Error bounds that hold: every method keeps its output within the bound it was given.

The bound (a fraction of the diagonal) is the most the output may deviate from the input
surface, two-sided, in mm, measured at the points the contract names: every input vertex
to the output surface, every output vertex, edge midpoint and triangle centroid to the
input surface. The decimation checks itself (``miss.measure._jit.bound_check``, on the new
edges and triangles only; a schroeder model, within its bound by construction, without
the triangles' centroids); these tests measure all those points again, on every edge and
triangle of the output, with nothing of the check's bookkeeping.

Between those points two surfaces can part further (a new edge along a wavy input surface,
a valley of the output under an input triangle). Schroeder's accumulated error is a bound
everywhere (``miss.decimate._fan.overlay_gap``), so its models are also measured densely
here (every output edge at each eighth, random points inside both surfaces); a quadric
model (the paper's schedule only) is held at the checked points alone.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_schroeder import icosphere  # the same sphere as the kernel's tests

from miss import Mesh, decimate
from miss.measure._jit import between, distances_to

BOUNDS = (0.0001, 0.0002, 0.0005, 0.001, 0.002, 0.01)


def box(n: int, size: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Closed box (mm) centred on 0, each side an n x n grid, welded: sharp creases and
    corners; a small third size makes a thin plate (two sheets close together)."""
    g = np.linspace(-0.5, 0.5, n)
    u, w = (c.ravel() for c in np.meshgrid(g, g, indexing="xy"))
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="xy")
    a = (j * n + i).ravel()
    quads = np.concatenate([np.stack([a, a + 1, a + n + 1], 1), np.stack([a, a + n + 1, a + n], 1)])
    verts, faces = [], []
    for axis in range(3):
        others = [k for k in range(3) if k != axis]
        for sign in (-1.0, 1.0):
            p = np.zeros((n * n, 3))
            p[:, axis], p[:, others[0]], p[:, others[1]] = sign * 0.5, u, w
            outward = (sign > 0) == ((axis + 1) % 3 == others[0])
            faces.append((quads if outward else quads[:, ::-1]) + len(verts) * n * n)
            verts.append(p)
    v, inverse = np.unique(np.round(np.concatenate(verts), 9), axis=0, return_inverse=True)
    return v * np.asarray(size), inverse.ravel()[np.concatenate(faces)].astype(np.int32)


def scene(kind: str, seed: int, noise: float, pieces: int) -> Mesh:
    """A test surface in mm: a noisy sphere, a thin plate or a creased box, with ``pieces``
    small loose spheres (bone chips) beside it."""
    rng = np.random.default_rng(seed)
    if kind == "sphere":
        v, f = icosphere(4)
        v = v * 50.0
    elif kind == "plate":
        v, f = box(16, (80.0, 60.0, 0.6))
    else:
        v, f = box(12, (60.0, 40.0, 30.0))
    v = v + noise * rng.standard_normal(v.shape)
    parts_v, parts_f = [v], [f]
    for k in range(pieces):
        sv, sf = icosphere(1)
        parts_f.append(sf + sum(len(p) for p in parts_v))
        parts_v.append(sv * rng.uniform(0.5, 2.0) + [70.0 + 6.0 * k, rng.uniform(-20, 20), 0.0])
    return Mesh(np.concatenate(parts_v).astype(np.float32), np.concatenate(parts_f))


def independent_max(before: Mesh, after: Mesh) -> float:
    """Max distance (mm) at the contract's points: every input vertex to the output; every
    output vertex, edge midpoint and triangle centroid (of all its triangles, new or kept)
    to the input."""
    to_after = distances_to(before.vertices[np.unique(before.faces)], after)
    v, f = after.vertices.astype(np.float64), after.faces
    mids = np.concatenate([0.5 * (v[f[:, k]] + v[f[:, (k + 1) % 3]]) for k in range(3)])
    back = distances_to(np.concatenate([v, mids, v[f].mean(axis=1)]), before)
    return float(max(to_after.max(), back.max()))


def dense_max(before: Mesh, after: Mesh, samples: int = 200_000) -> float:
    """Max distance (mm) between the contract's points (:func:`miss.measure._jit.between`:
    every output edge at each eighth, every input edge's midpoint, random points inside
    both surfaces' triangles, both ways)."""
    return between(before, after, samples, seed=1)


@settings(
    max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True
)
@given(
    kind=st.sampled_from(["sphere", "plate", "box"]),
    seed=st.integers(0, 2**16),
    noise=st.sampled_from([0.0, 0.02, 0.2]),
    pieces=st.integers(0, 3),
    method=st.sampled_from(["quadric", "schroeder"]),
    bound=st.sampled_from(BOUNDS),
    schedule=st.sampled_from(["guaranteed", "paper"]),
)
@pytest.mark.slow
def test_output_within_its_bound(
    kind: str, seed: int, noise: float, pieces: int, method: str, bound: float, schedule: str
) -> None:
    mesh = scene(kind, seed, noise, pieces)
    out, report = decimate(mesh, method, reduce=0.9, error_bound=bound, schedule=schedule)
    slack = 1e-6 * mesh.diagonal()
    if schedule == "guaranteed":
        assert report.bound_mm == pytest.approx(bound * mesh.diagonal())
    assert report.bound_held
    assert report.max_error_mm <= report.bound_mm + slack
    assert independent_max(mesh, out) <= report.bound_mm + slack
    if report.finished_with == "schroeder":  # held everywhere, not only where measured
        assert dense_max(mesh, out, samples=50_000) <= report.bound_mm + slack
    if schedule == "guaranteed" and method != "none":
        assert report.finished_with == "schroeder"  # quadric's estimate is no bound
    assert report.stopped_by == ("reduce" if report.achieved_reduction >= 0.9 else "bound")


def test_between_the_checked_points_the_bound_holds_too() -> None:
    # found by a wider run of the property test above (random examples, 2026-11-27): held at
    # every checked point (0.1737 mm against 0.1738), yet 0.195 mm between them, where a
    # deletion's share of the error was measured at points (v, the spokes' and chords'
    # midpoints, the triangles' centroids) instead of bounded
    mesh = scene("sphere", 0, 0.2, 0)
    out, report = decimate(mesh, "quadric", reduce=0.5, error_bound=0.001)
    assert report.bound_held
    assert independent_max(mesh, out) <= report.bound_mm + 1e-6 * mesh.diagonal()
    assert dense_max(mesh, out) <= report.bound_mm + 1e-6 * mesh.diagonal()


@pytest.mark.parametrize("method", ["quadric", "schroeder"])
def test_a_loose_bound_meets_reduce_and_says_so(method: str) -> None:
    mesh = scene("sphere", 0, 0.0, 0)
    _, report = decimate(mesh, method, reduce=0.5, error_bound=0.01)
    assert report.stopped_by == "reduce" and report.achieved_reduction >= 0.5
    # held to the bound asked for, not to the lower one schroeder's rising bound stopped at
    assert report.bound_mm == pytest.approx(0.01 * mesh.diagonal())
    assert report.bound_held and report.max_error_mm <= report.bound_mm


@pytest.mark.parametrize("method", ["quadric", "schroeder"])
def test_a_tight_bound_stops_decimation_and_says_so(method: str) -> None:
    mesh = scene("sphere", 0, 0.2, 0)
    _, report = decimate(mesh, method, reduce=0.99, error_bound=0.0001)
    assert report.stopped_by == "bound" and report.achieved_reduction < 0.99
    assert report.bound_held and report.max_error_mm <= report.bound_mm + 1e-6


def test_the_report_says_what_the_contract_asks() -> None:
    mesh = scene("box", 0, 0.02, 1)
    _, report = decimate(mesh, "quadric", reduce=0.9, error_bound=0.001)
    summary = report.summary()
    for key in ("stopped_by", "max_error_mm", "mean_error_mm", "bound_mm", "achieved_reduction"):
        assert summary[key] is not None
    assert summary["schedule"] == "guaranteed"


def test_the_check_does_not_wait_for_a_starved_thread(monkeypatch) -> None:
    # the input's grid is made on a thread at nice 19 while the run goes on; where that
    # thread gets no core (a busy machine), the check makes the grid itself rather than
    # wait, and the job ends with the thread still held
    import importlib
    import threading

    module = importlib.import_module("miss.decimate")
    held, finished = threading.Event(), threading.Event()

    def starved() -> None:
        held.wait(60)
        finished.set()

    mesh = scene("box", 0, 0.02, 1)
    _, free = decimate(mesh, "schroeder", reduce=0.9, error_bound=0.001)
    monkeypatch.setattr(module, "_idle_priority", starved)
    try:
        out, report = decimate(mesh, "schroeder", reduce=0.9, error_bound=0.001)
        assert not finished.is_set()  # the job did not wait for the thread
    finally:
        held.set()
    assert report.bound_held and report.max_error_mm == free.max_error_mm
    assert out.n_triangles == free.triangles_out


def test_a_run_far_out_is_screened_and_a_guaranteed_bound_is_schroeders() -> None:
    # a quadric run (the paper's schedule) that strays is known out of bound from a few of
    # its dropped vertices; under a guaranteed bound quadric does not run: schroeder makes
    # the model in one run, held everywhere
    from miss.decimate import _strays
    from miss.measure._jit import bound_check

    mesh = scene("sphere", 3, 0.2, 0)
    top = mesh.vertices[mesh.faces].mean(axis=1)[:, 2] > 0
    quadric_faces = mesh.faces[top]  # the upper half of the sphere: the lower far out
    assert _strays(mesh, quadric_faces, 0.01 * mesh.diagonal())
    assert not _strays(mesh, mesh.faces, 1e-9)  # nothing dropped
    out, report = decimate(mesh, "quadric", reduce=0.99, error_bound=0.0005)
    assert report.method == "quadric"
    assert report.finished_with == "schroeder" and report.rounds == 1
    check = bound_check(mesh, np.asarray(out.faces))  # out's vertices are compacted
    assert report.bound_held and report.max_error_mm <= report.bound_mm + 1e-6
    assert independent_max(mesh, out) <= report.bound_mm + 1e-6 * mesh.diagonal()
    assert dense_max(mesh, out) <= report.bound_mm + 1e-6 * mesh.diagonal()
    assert check.samples > 0


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**16), noise=st.sampled_from([0.02, 0.2]))
@pytest.mark.slow
def test_vertices_out_of_bound_are_put_back_on_the_surface(seed: int, noise: float) -> None:
    # a run whose edges and triangles are within a bound but a few dropped input vertices
    # are not: each goes back into the triangle nearest to it, split in three, and lies
    # on the surface again; the mended mesh is still closed, with the same topology
    from hypothesis import assume
    from test_schroeder import boundary_edges, euler_characteristic

    from miss.decimate import _put_back
    from miss.decimate._schroeder import schroeder_decimate
    from miss.measure._jit import bound_check

    mesh = scene("sphere", seed, noise, 0)
    bound = 0.002 * mesh.diagonal()
    faces, _ = schroeder_decimate(
        mesh.vertices.astype(np.float64), mesh.faces, reduce=0.99, error_bound=bound / 8,
        max_error=bound,
    )  # fmt: skip
    check = bound_check(mesh, faces)
    # a limit the new edges and triangles keep and a few dropped vertices do not
    limit = max(check.edge_mm.max(), check.face_mm.max()) * 1.0001
    stray = np.flatnonzero(np.nan_to_num(check.to_output) > limit)
    assume(0 < len(stray) <= 64)
    mended = _put_back(mesh, faces, check, limit)
    assume(mended is not None)  # a foot outside its triangle: the caller runs again
    assert len(mended) == len(faces) + 2 * len(stray)
    again = bound_check(mesh, mended)
    assert np.all(again.to_output[stray] == 0.0)
    assert len(boundary_edges(mended)) == 0
    assert euler_characteristic(mended) == euler_characteristic(faces)
    assert _put_back(mesh, faces, check, 0.0) is None  # edges out too: not for mending


def _tent(top: tuple[float, float, float]) -> tuple[Mesh, np.ndarray]:
    """A square fan around a raised vertex (the input), and the square's two triangles
    across the diagonal a-c without it (the output)."""
    verts = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0], top], dtype=np.float32)
    fan = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]], dtype=np.int32)
    return Mesh(verts, fan), np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)


def test_a_vertex_beside_an_edge_splits_the_edge() -> None:
    # its foot lies on the diagonal both triangles share: no triangle holds it for a split
    # in three, so the edge is split and its two triangles become four that meet at it
    from miss.decimate import _put_back
    from miss.measure._jit import bound_check

    mesh, square = _tent((5.0, 5.0, 1.0))
    check = bound_check(mesh, square)
    limit = max(check.edge_mm.max(), check.face_mm.max()) * 1.0001  # the vertex alone out
    assert check.to_output[4] == pytest.approx(1.0) and limit < 1.0
    mended = _put_back(mesh, square, check, limit)
    assert mended is not None and len(mended) == 4
    assert (mended == 4).any(axis=1).all()  # every triangle meets the vertex put back
    assert bound_check(mesh, mended).max_mm == pytest.approx(0.0, abs=1e-6)
    v = mesh.vertices.astype(np.float64)[mended]
    normals = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    assert (normals[:, 2] > 0).all()  # none turned over
    near_corner, square = _tent((0.05, 0.05, 1.0))
    check = bound_check(near_corner, square)
    limit = max(check.edge_mm.max(), check.face_mm.max()) * 1.0001
    assert check.to_output[4] > limit
    assert _put_back(near_corner, square, check, limit) is None


def test_a_schroeder_run_a_little_out_is_mended_not_run_again(datasets) -> None:
    # CThead bone at 0.0005: the first run leaves one dropped vertex 6 % over the bound;
    # it is put back and the model is the first run's, held, in one round
    from miss.decimate import decimate

    surface = miss_surface(datasets)
    out, report = decimate(surface, "schroeder", reduce=0.99, error_bound=0.0005)
    assert report.rounds == 1 and report.bound_held
    assert report.max_error_mm <= report.bound_mm + 1e-6 * surface.diagonal()
    assert independent_max(surface, out) <= report.bound_mm + 1e-6 * surface.diagonal()


def miss_surface(datasets) -> Mesh:
    from miss import extract_surface, load_volume

    volume = load_volume(datasets / "ct_head_stanford_cthead" / "CThead.nhdr")
    return extract_surface(volume, 1500.0, normals=False)


def test_a_schroeder_model_is_checked_at_the_contracts_points(monkeypatch) -> None:
    """A model schroeder made is within its bound by construction: its check measures the
    contract's points (every input vertex, every new edge's midpoint), not the new
    triangles' centroids too; a quadric model (the paper's schedule) is held only where it
    is measured, so its check keeps them. The max is the same either way here."""
    import miss.measure as measure  # where the decimation takes its check from

    asked: list[bool] = []
    real = measure.bound_check

    def spy(*args: object, **kwargs: object) -> measure.BoundCheck:
        asked.append(args[5] if len(args) > 5 else kwargs.get("centroids", True))
        return real(*args, **kwargs)

    monkeypatch.setattr(measure, "bound_check", spy)
    mesh = scene("sphere", 0, 0.2, 0)
    out, report = decimate(mesh, "quadric", reduce=0.9, error_bound=0.002)
    assert report.finished_with == "schroeder" and asked == [False]
    asked.clear()
    _, paper = decimate(mesh, "quadric", reduce=0.9, error_bound=0.002, schedule="paper")
    assert paper.finished_with == "quadric" and asked[0] is True

    from miss.decimate.schroeder import schroeder

    bound_mm = report.bound_mm
    faces, _ = schroeder(mesh, 0.9, bound_mm / 8, bound_mm)  # what decimate ran, uncompacted
    full, lean = real(mesh, faces), real(mesh, faces, centroids=False)
    assert len(lean.faces) == len(lean.face_mm) == 0 < len(full.face_mm)
    assert np.array_equal(lean.edges, full.edges) and np.array_equal(lean.edge_mm, full.edge_mm)
    assert lean.max_mm == full.max_mm == report.max_error_mm
