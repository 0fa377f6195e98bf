"""The benchmark's machinery: resampling, the paper-table rows, the CLI entry, and the two
performance paths it relies on (exact fast deviation, parallel quadric decimation)."""

from __future__ import annotations

import importlib
import json
from pathlib import Path

import measure as measure_bench  # benchmarks/ (pyproject: pythonpath), not the package
import numpy as np
import paper as bench
import paper_tables
import pytest
from paper import MODES, SAMPLE_RATES, markdown, paper_rows, resample_axis

from miss import BadParameter, Mesh, Volume, decimate, extract_surface
from miss.demo import phantom
from miss.geometry import boundary_edge_count, enclosed_volume
from miss.measure._jit import deviation, distances_to

# the package exports the function decimate under the module's name
decimate_module = importlib.import_module("miss.decimate.quadric")
PHANTOM_LEVELS = {"bone": 300.0, "skin": -500.0}  # HU, see miss.demo


def test_resample_keeps_a_linear_ramp_and_the_physical_extent() -> None:
    k = np.arange(5, dtype=np.float64)
    data = np.broadcast_to(100 * k, (3, 4, 5)).astype(np.int16)
    affine = np.diag([1.0, 1.0, 2.0, 1.0])
    affine[:3, 3] = (7.0, 8.0, 9.0)
    out = resample_axis(Volume(np.asfortranarray(data), affine), 2, 9)
    assert out.data.shape == (3, 4, 9) and out.data.dtype == np.int16
    assert out.data.flags.f_contiguous
    np.testing.assert_array_equal(out.data[1, 2], np.arange(9) * 50)
    last = out.affine @ [0, 0, 8, 1]
    np.testing.assert_allclose(last[:3], (affine @ [0, 0, 4, 1])[:3])  # same last slice
    assert out.spacing == pytest.approx((1.0, 1.0, 1.0))


def test_resample_refuses_fewer_than_two_samples() -> None:
    with pytest.raises(BadParameter, match="at least 2 samples"):
        resample_axis(phantom(16), 0, 1)


def test_paper_rows_on_the_phantom() -> None:
    rows = paper_rows(
        phantom(64, spacing=3.0),
        repeats=1,
        sample_rates=(4,),
        method="quadric",
        levels=PHANTOM_LEVELS,
    )
    assert [(r.tissue, r.sample_rate, r.mode) for r in rows] == [
        (t, 4, m) for t in PHANTOM_LEVELS for m in MODES
    ]
    by_mode = {(r.tissue, r.mode): r for r in rows}
    for tissue in PHANTOM_LEVELS:
        m, md, md2 = (by_mode[(tissue, mode)] for mode in MODES)
        assert m.reduction == 0.0 and m.max_error_mm == 0.0
        # the larger bound removes more and errs more, as in the paper
        assert m.triangles >= md.triangles >= md2.triangles > 0
        assert md2.mean_error_mm >= md.mean_error_mm >= 0.0
        assert m.vrml_kb > md2.vrml_kb > 0
        assert m.seconds > 0 and len(m.seconds_runs) == 1
        paper = {"bone": (35744, 2656), "skin": (42756, 3200)}[tissue]
        assert (m.paper_triangles, m.paper_vrml_kb) == paper
    table = markdown(rows)
    assert table.count("\n| 4 |") == 6
    assert "paper triangles" in table and "mean error mm" in table
    assert "| 4 | MD2 |" in table and "illegible" in table  # bone MD at rate 4 in the scan


def test_paper_plot_is_a_png(tmp_path) -> None:
    pytest.importorskip("matplotlib")
    from paper import plot

    rows = paper_rows(
        phantom(48, spacing=4.0),
        repeats=1,
        sample_rates=(4, 2),
        method="quadric",
        levels={"bone": 300.0},
    )
    plot(rows, tmp_path / "t.png")
    assert (tmp_path / "t.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_paper_tables_rejects_bad_sample_rates(capsys) -> None:
    assert paper_tables.main(["--sample-rates", "one"]) == 2
    assert "--sample-rates must be integers" in capsys.readouterr().err


def test_paper_tables_writes_the_three_files(tmp_path, monkeypatch, capsys) -> None:
    pytest.importorskip("matplotlib")
    monkeypatch.setattr(bench, "paper_volume", lambda path=None: phantom(48, spacing=4.0))
    monkeypatch.setattr(bench, "LEVELS", {"bone": 300.0})
    monkeypatch.setattr(bench, "decimation_method", lambda: "quadric")  # no numba compile
    argv = ["--out", str(tmp_path), "--repeats", "1", "--sample-rates", "4"]
    assert paper_tables.main(argv) == 0
    data = json.loads((tmp_path / "paper_tables.json").read_text())
    assert len(data["rows"]) == 3 and data["machine"]["cores"] >= 1
    assert (tmp_path / "paper_tables.md").is_file() and (tmp_path / "paper_tables.png").is_file()
    assert "| 4 | MD |" in capsys.readouterr().out
    assert SAMPLE_RATES == (1, 2, 4)


def test_cli_benchmark_times_whole_processes(tmp_path: Path) -> None:
    """benchmarks/cli.py in a quick mode: one round of every command on a small phantom."""
    pytest.importorskip("trimesh")
    import cli
    from common import write_nifti

    small = write_nifti(phantom(48, spacing=4.0), tmp_path / "small.nii")
    argv = ["--repeats", "1", "--volume", str(small), "--info", str(small), "--level", "300"]
    assert cli.main([*argv, "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "cli.json").read_text())
    expected = {cli.HELP, cli.INFO, cli.CONVERT, cli.MEASURED, cli.HELD, cli.PEER}
    assert set(data["timing"]) == expected
    for timing in data["timing"].values():
        assert timing["seconds"] > 0 and timing["rss_mib"] > 0 and len(timing["runs"]) == 1
    for result in data["deviation"].values():
        assert 0 < result["triangles"] < result["triangles_before"]
        assert result["mean_error_mm"] <= result["max_error_mm"] < 10
    assert "| peer script |" in (tmp_path / "cli.md").read_text()


# ----------------------------------------------------------------------------- deviation


def _brute_force(points: np.ndarray, mesh: Mesh) -> np.ndarray:
    """Distance to every triangle, by projecting onto each plane and each edge (slow, obvious)."""
    tri = mesh.vertices.astype(np.float64)[mesh.faces]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    flat = length[:, 0] > 1e-12  # zero-area triangles are covered by their edges below
    n = np.divide(n, length, out=np.zeros_like(n), where=length > 1e-12)
    best = np.full(len(points), np.inf)
    for i, p in enumerate(points):
        q = p - ((p - a) * n).sum(axis=1)[:, None] * n  # projection onto each plane
        inside = flat.copy()
        for u, v in ((a, b), (b, c), (c, a)):
            inside &= (np.cross(v - u, q - u) * n).sum(axis=1) >= 0
        d = np.where(inside, np.linalg.norm(p - q, axis=1), np.inf)
        for u, v in ((a, b), (b, c), (c, a)):
            length2 = np.maximum(((v - u) ** 2).sum(axis=1), 1e-300)  # a zero edge is a point
            t = np.clip(((p - u) * (v - u)).sum(axis=1) / length2, 0, 1)
            d = np.minimum(d, np.linalg.norm(p - (u + t[:, None] * (v - u)), axis=1))
        best[i] = d.min()
    return best


@pytest.fixture(scope="module")
def skull() -> Mesh:
    return extract_surface(phantom(), 300.0, sample_rate=4)


def test_distances_are_exact(skull: Mesh) -> None:
    coarse, _ = decimate(skull, "quadric", reduce=0.95, measure=False)
    rng = np.random.default_rng(3)
    lo, hi = skull.bounds()
    points = np.concatenate(
        [
            rng.uniform(lo - 30, hi + 30, (150, 3)),  # near, inside, and far outside
            skull.vertices[rng.choice(skull.n_vertices, 100)].astype(np.float64),
        ]
    )
    for target in (skull, coarse):
        np.testing.assert_allclose(
            distances_to(points, target), _brute_force(points, target), rtol=1e-9, atol=1e-6
        )


def test_distances_are_exact_on_slivers_and_points_off_the_grid(degenerate_mesh: Mesh) -> None:
    """A zero-area triangle counts by its edges; points far outside the mesh's box, on every
    side, search outwards until the whole grid is covered."""
    mesh = Mesh(degenerate_mesh.vertices.astype(np.float32), degenerate_mesh.faces.astype(np.int32))
    rng = np.random.default_rng(5)
    points = np.concatenate(
        [rng.uniform(-40, 40, (200, 3)), rng.uniform(-0.5, 2.5, (200, 3)), mesh.vertices[:5]]
    )
    np.testing.assert_allclose(
        distances_to(points, mesh), _brute_force(points, mesh), rtol=1e-9, atol=1e-6
    )


def test_samples_are_the_vertices_and_points_inside_triangles(skull: Mesh) -> None:
    from miss.measure._jit import sample_surface

    points = sample_surface(skull, 4000, np.random.default_rng(1))
    assert points.shape == (4000, 3) and points.dtype == np.float64
    corners = {tuple(v) for v in skull.vertices.astype(np.float64).tolist()}
    assert all(tuple(p) in corners for p in points[:2000].tolist())
    assert distances_to(points[2000:], skull).max() < 1e-4  # on the surface


def test_deviation_is_zero_to_itself_and_symmetric_in_its_samples(skull: Mesh) -> None:
    assert deviation(skull, skull, samples=5000).max_mm == pytest.approx(0.0, abs=1e-5)
    shifted = Mesh(skull.vertices + np.float32(0.25), skull.faces)
    dev = deviation(skull, shifted, samples=5000)
    assert 0.0 < dev.mean_mm <= dev.max_mm <= np.sqrt(3) * 0.25 + 1e-5


def test_measure_benchmark_writes_its_table(tmp_path, capsys) -> None:
    """benchmarks/measure.py in a quick mode: one small scan, one run of each kind."""
    case = "MR headsq skin"
    if not measure_bench.cases()[case][0].is_file():
        pytest.skip("../shared/datasets is not beside the repository")
    argv = ["--cases", case, "--repeats", "1", "--fresh-repeats", "1", "--out", str(tmp_path)]
    assert measure_bench.main(argv) == 0
    data = json.loads((tmp_path / "measure.json").read_text())
    (row,) = data["rows"]
    assert row[0] == case and row[1] > 10_000
    new_max, old_max, new_mean, old_mean = row[11:15]
    if not np.isnan(old_max):  # git history at hand: the same figures as before
        assert new_max == pytest.approx(old_max, rel=0.01)
        assert new_mean == pytest.approx(old_mean, rel=0.01)
    assert "share % (fresh)" in (tmp_path / "measure.md").read_text()
    # the measuring job as MISS runs it: its figures are the measurement's own
    (piped,) = data["pipeline"]
    assert piped[0] == case and piped[8:10] == pytest.approx(row[11:15:2])
    assert piped[10] == "yes"  # `miss convert --measure`, fresh, measured the same
    assert "added % (fresh)" in (tmp_path / "measure.md").read_text()
    # the same queries by MISS's two searches and the peers: the same figures
    peers = {search: figures for _, search, _, *figures in data["peers"]}
    assert peers["MISS native"] == peers["MISS numba"] == pytest.approx(row[11:15:2])
    for search in ("libigl AABB", "FCPW BVH"):
        assert peers[search] == pytest.approx(peers["MISS native"], rel=1e-5)
    assert "| MR headsq skin |" in capsys.readouterr().out


# ----------------------------------------------------------------------------- parallel quadric


def test_two_phase_quadric_meets_the_target_and_stays_closed(monkeypatch) -> None:
    mesh = extract_surface(phantom(), 300.0, sample_rate=2)
    monkeypatch.setattr(decimate_module, "_PARALLEL_MIN_TRIANGLES", 1000)
    out, report = decimate(mesh, "quadric", reduce=0.9, samples=20_000, schedule="paper")
    assert abs(out.n_triangles - 0.1 * mesh.n_triangles) <= 0.01 * mesh.n_triangles
    assert boundary_edge_count(out.faces) == 0
    assert enclosed_volume(out.vertices, out.faces) == pytest.approx(
        enclosed_volume(mesh.vertices, mesh.faces), rel=0.02
    )
    original = {tuple(v) for v in mesh.vertices.tolist()}
    assert all(tuple(v) in original for v in out.vertices.tolist())
    assert report.max_error_mm is not None and report.max_error_mm < 0.02 * mesh.diagonal()


# ----------------------------------------------------------------------------- slab surface


@pytest.mark.parametrize("level", [300.0, -500.0])
def test_slabs_give_the_whole_blocks_surface(monkeypatch, level: float) -> None:
    from scipy.spatial import cKDTree

    surface = importlib.import_module("miss.surface")
    block = phantom(96, spacing=2.0).data
    contour = surface.contour_level(block.dtype, level)
    span = float(block.max() - block.min())
    monkeypatch.setattr(surface, "_SLAB_VOXELS", 96 * 96 * 20)
    assert len(surface._seam_planes(block, contour)) >= 3
    v1, f1, n1 = surface._surface_in_slabs(block, contour, span)
    v2, f2, n2 = surface._surface_whole(block, contour, span)
    dist, to_whole = cKDTree(v2).query(v1)
    assert dist.max() < 1e-4 and len(np.unique(to_whole)) == len(v2) == len(v1)
    np.testing.assert_allclose(n1, n2[to_whole], atol=1e-6)  # central differences on seams

    def canonical(faces: np.ndarray) -> np.ndarray:
        # rotate each triangle to start at its smallest index: keeps the winding comparable
        first = np.argmin(faces, axis=1)
        rolled = np.stack([faces[np.arange(len(faces)), (first + k) % 3] for k in range(3)], 1)
        return rolled[np.lexsort(rolled.T[::-1])]

    np.testing.assert_array_equal(canonical(to_whole[f1]), canonical(f2))


def test_a_voxel_at_the_level_is_inside_and_makes_no_degenerate_triangle() -> None:
    data = np.zeros((9, 5, 5), dtype=np.int16)
    data[2, 2, 2] = 100  # exactly at the level: inside, a small octahedron around it
    data[6, 2, 2] = 150
    mesh = extract_surface(Volume(data, np.eye(4)), 100.0)
    assert mesh.n_triangles == 16  # two octahedra
    tri = mesh.vertices[mesh.faces]
    assert (
        np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) > 0
    ).all()


def test_the_paper_volume_is_looked_for_beside_the_repository(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``../shared`` next to the checkout, as the README and CI have it (the file moved
    out of the package once and looked one folder too high)."""
    monkeypatch.delenv("MISS_CTHEAD", raising=False)
    repo = Path(__file__).resolve().parents[1]
    expected = repo.parent / "shared" / "datasets" / "ct_head_stanford_cthead" / "CThead.nhdr"
    assert bench.default_cthead() == expected
    monkeypatch.setenv("MISS_CTHEAD", "/elsewhere/CThead.nhdr")
    assert bench.default_cthead() == Path("/elsewhere/CThead.nhdr")


def test_bounds_rows_on_the_phantom() -> None:
    """``benchmarks/bounds.py``: MISS's methods within each bound, peers at MISS's count,
    every output measured the same way (here, not by the method)."""
    import bounds

    mesh = extract_surface(phantom(48, spacing=4.0), 200.0)
    case = bounds.bench_case(mesh, (0.001, 0.01), peers=True, log=lambda line: None, samples=20_000)
    assert case["unbounded_quadric_seconds"] > 0
    for entry in case["bounds"].values():
        rows = {r["method"]: r for r in entry["rows"]}
        assert set(rows) == {"MISS quadric", "MISS schroeder", "MISS placed", *bounds.PEERS}
        for name in ("MISS quadric", "MISS schroeder", "MISS placed"):
            assert rows[name]["holds"] and rows[name]["max_mm"] <= entry["bound_mm"] * 1.000001
        for row in rows.values():  # the dense measure adds points: never less than the checked
            assert row["dense_max_mm"] >= row["max_mm"]
            assert row["holds_densely"] == (
                row["dense_max_mm"] <= entry["bound_mm"] + 1e-6 * mesh.diagonal()
            )
        best = min(rows[f"MISS {m}"]["triangles"] for m in ("quadric", "schroeder", "placed"))
        assert abs(rows["pyfqmr"]["triangles"] - best) <= 0.02 * best + 2
    assert len(bounds.verdict(case)) == 2
    import report

    (line,) = report.bounds_targets({"cases": {"phantom": case}})
    dense = sum(
        min((r for r in e["rows"] if r["method"].startswith("MISS") and r["holds"]),
            key=lambda r: (r["triangles"], r["seconds"]))["holds_densely"]
        for e in case["bounds"].values()
    )  # fmt: skip
    assert f"held between the checked points too (dense max) at {dense} of 2" in line
    table = bounds.markdown({"cases": {"phantom": case}})
    assert "| 0.001 |" in table and "MISS schroeder" in table and "holds densely" in table


def test_bounds_rejects_bad_bounds_and_cases(capsys) -> None:
    import bounds

    assert bounds.main(["--bounds", "tight"]) == 2
    assert "--bounds must be numbers" in capsys.readouterr().err
    assert bounds.main(["--cases", "CThead knee"]) == 2
    assert "unknown case" in capsys.readouterr().err


def test_scale_volume_is_stored_as_miss_stores_one(tmp_path: Path) -> None:
    """``benchmarks/scale.py`` measures the format MISS stores (Zarr in 64³ chunks, read
    through ``Voxels``): its resampled CThead, blockwise on threads, gives the same
    triangles as the single pass on the same (padded) region."""
    if not bench.default_cthead().is_file():
        pytest.skip("CThead is absent: the real scans live in ../shared/datasets")
    import scale

    from miss.server.storage import chunked
    from miss.surface.blockwise import blockwise_surface

    path = scale.make_volume((72, 70, 40), tmp_path)
    voxels, affine, _ = chunked.open_array(path)
    assert voxels.shape == (72, 70, 40) and voxels.chunks == (64, 64, 40)
    assert np.array_equal(affine, np.eye(4))
    whole = Volume(np.asarray(voxels), affine)
    lazy = Volume(voxels, affine)
    single = extract_surface(whole, scale.LEVEL, normals=False)
    blocks = blockwise_surface(lazy, scale.LEVEL, normals=False, block=16, cluster=False)
    assert blocks.n_triangles == single.n_triangles > 1000
