"""Blockwise surfaces equal the single pass: the same triangles and vertices, closed, the
same volume, at any block size (7 voxels, uneven blocks), from numpy or Zarr."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from miss import BadParameter, EmptySurface, Volume, extract_surface
from miss.geometry import boundary_edge_count, enclosed_volume
from miss.surface.blocks import Grid, voxel_boxes
from miss.surface.blockwise import RANGE_BLOCK, blockwise_surface
from miss.types import Mesh

# extract_surface keeps VTK's float32 vertices (index space, then mm); blockwise places
# them from float64 edge parameters: they differ by float32 rounding only, ~1 ulp at the
# coordinates' size (1.5e-5 mm at 128-256 mm).
FLOAT32_ROUNDING_MM = 4e-5


def _canonical(faces: np.ndarray) -> np.ndarray:
    """Triangles rotated to start at their smallest index (winding kept), rows sorted."""
    roll = np.argmin(faces, axis=1)
    rows = np.arange(len(faces))[:, None]
    turned = faces[rows, (roll[:, None] + np.arange(3)) % 3]
    return turned[np.lexsort(turned.T[::-1])]


def assert_same_surface(got: Mesh, want: Mesh, tol_mm: float) -> None:
    """Same vertex count, each vertex within ``tol_mm`` of its own partner (a bijection),
    the same triangles (same winding) through that pairing, the same enclosed volume."""
    assert got.n_triangles == want.n_triangles
    assert len(got.vertices) == len(want.vertices)
    dist, partner = cKDTree(want.vertices).query(got.vertices)
    assert dist.max() <= tol_mm
    assert len(np.unique(partner)) == len(partner)
    np.testing.assert_array_equal(_canonical(partner[got.faces]), _canonical(want.faces))
    assert boundary_edge_count(got.faces) == 0
    got_ml = enclosed_volume(got.vertices, got.faces) / 1000
    want_ml = enclosed_volume(want.vertices, want.faces) / 1000
    assert got_ml == pytest.approx(want_ml, abs=1e-6 if tol_mm == 0 else 1e-4)


def zarr_copy(volume: Volume, folder: Path, chunks: tuple[int, int, int]) -> Volume:
    import zarr

    array = zarr.create_array(
        folder / "volume.zarr", shape=volume.data.shape, chunks=chunks, dtype=volume.data.dtype
    )
    array[...] = volume.data
    return Volume(zarr.open_array(folder / "volume.zarr", mode="r"), volume.affine, volume.meta)


@pytest.fixture(scope="module")
def cthead(datasets: Path) -> Volume:
    from miss.io import load_volume

    return load_volume(datasets / "ct_head_stanford_cthead" / "CThead.nhdr")


@pytest.fixture(scope="module")
def mr_head(datasets: Path) -> Volume:
    from miss.io import load_volume

    return load_volume(datasets / "mr_head_dicom_vsseg001_t1")


@pytest.fixture(scope="module")
def cthead_reference(cthead: Volume) -> tuple[Mesh, Mesh]:
    """extract_surface's bone, and the blockwise one-block run (one flying-edges pass over
    the whole padded region)."""
    single = extract_surface(cthead, 1500.0, normals=False)
    one_block = blockwise_surface(cthead, 1500.0, normals=False, block=10_000)
    return single, one_block


@pytest.mark.parametrize("block", [7, 32, (50, 37, 29)])
@pytest.mark.slow
def test_cthead_blockwise_equals_single_pass(cthead, cthead_reference, block) -> None:
    single, one_block = cthead_reference
    mesh = blockwise_surface(cthead, 1500.0, normals=False, block=block)
    assert_same_surface(mesh, one_block, 0.0)  # bit for bit, whatever the blocks
    assert_same_surface(mesh, single, FLOAT32_ROUNDING_MM)


def test_cthead_from_zarr_chunks_equals_numpy(cthead, cthead_reference, tmp_path) -> None:
    lazy = zarr_copy(cthead, tmp_path, (64, 64, 32))
    mesh = blockwise_surface(lazy, 1500.0, normals=False, block=(50, 37, 29))
    assert_same_surface(mesh, cthead_reference[1], 0.0)


@pytest.mark.parametrize("block", [32, (50, 37, 29)])
@pytest.mark.slow
def test_mr_head_blockwise_equals_single_pass(mr_head, block) -> None:
    single = extract_surface(mr_head, 300.0, normals=False)
    mesh = blockwise_surface(mr_head, 300.0, normals=False, block=block)
    assert_same_surface(mesh, single, FLOAT32_ROUNDING_MM)


@pytest.mark.slow
def test_mr_head_blocks_of_seven_from_zarr(mr_head, tmp_path) -> None:
    """Blocks of 7 over a quarter of the head (the whole one takes a minute here)."""
    roi = (100, 355, 60, 315, 20, 99)
    single = extract_surface(mr_head, 300.0, roi=roi, normals=False)
    lazy = zarr_copy(mr_head, tmp_path, (32, 32, 16))  # small chunks for small blocks
    mesh = blockwise_surface(lazy, 300.0, roi=roi, normals=False, block=7)
    assert_same_surface(mesh, single, FLOAT32_ROUNDING_MM)


def test_sample_rate_slices_and_normals(cthead) -> None:
    kwargs = {"sample_rate": (2, 3, 1), "slices": (20, 90)}
    single = extract_surface(cthead, 1000.0, **kwargs)
    mesh = blockwise_surface(cthead, 1000.0, block=(23, 17, 11), **kwargs)
    assert_same_surface(mesh, single, FLOAT32_ROUNDING_MM)
    _, partner = cKDTree(single.vertices).query(mesh.vertices)
    # gradient normals: the context voxels make them the same (zero where the gradient is)
    np.testing.assert_allclose(mesh.normals, single.normals[partner], atol=1e-5)


def test_float_data_and_mirrored_affine() -> None:
    """A float field (pad value from the span) on a left-handed grid keeps its winding."""
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in (41, 37, 33)], indexing="ij"), -1)
    data = np.asfortranarray((12.0 - np.linalg.norm(ijk - 18.0, axis=-1)).astype(np.float32))
    affine = np.diag([-0.7, 0.9, 1.3, 1.0])
    volume = Volume(data, affine, {"units": ""})
    single = extract_surface(volume, 0.37, normals=False)
    mesh = blockwise_surface(volume, 0.37, normals=False, block=(9, 8, 7))
    assert_same_surface(mesh, single, 1e-5)
    assert enclosed_volume(mesh.vertices, mesh.faces) > 0


def test_bad_level_and_block_size(cthead) -> None:
    with pytest.raises(EmptySurface, match="pick a level inside"):
        blockwise_surface(cthead, 99_999.0, block=64)
    with pytest.raises(BadParameter, match="block size"):
        blockwise_surface(cthead, 1000.0, block=0)


def test_progress_counts_blocks(cthead) -> None:
    """Integer data: one pass over the blocks (each reports its value range, checked once
    all are in); float data: the range pass first (its pad lies below the range)."""
    seen: list[tuple[str, float]] = []
    blockwise_surface(
        cthead, 1500.0, normals=False, block=100, progress=lambda s, f: seen.append((s, f))
    )
    blocks = 3 * 3 * 2  # 257 x 257 x 114 padded cells in blocks of 100
    assert len(seen) == blocks
    assert {s for s, _ in seen} == {"surface"}
    assert seen[-1][1] == pytest.approx(1.0)

    seen.clear()
    floats = Volume(np.asfortranarray(cthead.data, dtype=np.float32), cthead.affine)
    blockwise_surface(
        floats, 1500.0, normals=False, block=100, progress=lambda s, f: seen.append((s, f))
    )
    ranges = len(
        voxel_boxes(Grid(floats.data, (0, 0, 0), (1, 1, 1), (256, 256, 113), 0, "<f4"), RANGE_BLOCK)
    )
    assert len(seen) == ranges + blocks  # the range pass, then the surfaces
    assert seen[-1][1] == pytest.approx(1.0)


def test_a_level_outside_the_values_is_refused_after_one_pass(cthead) -> None:
    """Integer data's blocks would cap the whole region at a level below every voxel:
    the ranges they report refuse it as the single pass does."""
    low = float(cthead.data.min()) - 5
    with pytest.raises(EmptySurface, match="holds values"):
        blockwise_surface(cthead, low, normals=False, block=100)
    with pytest.raises(EmptySurface, match="holds values"):
        extract_surface(cthead, low, normals=False)


def test_a_job_on_zarr_goes_block_by_block(cthead, tmp_path) -> None:
    """The job's region stays lazy (read block by block) and its surface is the one the
    in-memory job makes; the progress comes from the blocks."""
    from miss.pipeline import run
    from miss.spec import JobSpec
    from miss.types import StridedView

    spec = JobSpec.of(level=1500, decimate="none", sample_rate=2, start_slice=10, end_slice=100)
    lazy = zarr_copy(cthead, tmp_path, (64, 64, 32))
    assert isinstance(spec.region.apply(lazy).data, StridedView)
    seen: list[float] = []
    got = run(lazy, spec, lambda stage, f: seen.append(f) if stage == "surface" else None)
    want = run(cthead, spec)
    assert got.mesh.n_triangles == want.mesh.n_triangles
    assert len(seen) > 2  # block by block, not just the stage's start
    assert enclosed_volume(got.mesh.vertices, got.mesh.faces) == pytest.approx(
        enclosed_volume(want.mesh.vertices, want.mesh.faces), rel=1e-6
    )


def test_cli_chunks_same_model(datasets, tmp_path) -> None:
    import json
    import subprocess
    import sys

    head = datasets / "ct_head_stanford_cthead" / "CThead.nhdr"

    def triangles(*extra: str) -> int:
        proc = subprocess.run(
            [sys.executable, "-m", "miss.cli", "convert", str(head), "--level", "1500",
             "--decimate", "none", "-o", str(tmp_path / "bone.stl"), "--json", *extra],
            capture_output=True, text=True, timeout=300, check=True,
        )  # fmt: skip
        return json.loads(proc.stdout)["triangles"]

    assert triangles("--chunks", "50,37,29") == triangles() == triangles("--chunks", "auto")


def _as_subset(full: Mesh, out: Mesh) -> np.ndarray:
    """``out``'s faces as indices into ``full``'s vertices (each of ``out``'s vertices is
    one of ``full``'s, at exactly its position: decimation moves none)."""
    index = {v: i for i, v in enumerate(map(tuple, full.vertices.tolist()))}
    return np.array([index[v] for v in map(tuple, out.vertices.tolist())])[out.faces]


@pytest.mark.parametrize(("method", "block"), [("quadric", 48), ("schroeder", (50, 37, 29))])
@pytest.mark.slow
def test_decimated_in_blocks_holds_the_bound_against_the_full_surface(
    cthead, method, block
) -> None:
    """Each block decimated where it was made (borders held), then across the blocks: the
    model, checked exactly against the full-resolution surface (every dropped vertex, every
    new edge's and triangle's middle), is within the bound, and within the report's max."""
    from miss.measure._jit import bound_check
    from miss.pipeline import run
    from miss.spec import JobSpec
    from miss.surface.blockwise import BlockRun

    spec = JobSpec.of(level=1500.0, decimate=method, reduce=0.9, error_bound=0.002)
    got = run(cthead, spec, blocks=BlockRun(block=block), measure=False)
    report = got.report
    full = blockwise_surface(cthead, 1500.0, normals=False, block=block)
    assert report.triangles_in == full.n_triangles
    assert report.triangles_out == got.mesh.n_triangles < 0.35 * full.n_triangles
    assert report.bound_mm == pytest.approx(0.002 * full.diagonal())
    exact = bound_check(full, _as_subset(full, got.mesh))
    slack = 1e-6 * full.diagonal()
    assert exact.max_mm <= report.bound_mm + slack
    assert exact.max_mm <= report.max_error_mm + slack <= report.bound_mm + 2 * slack
    assert report.bound_held and "decimated in its blocks" in got.scene.notes[0]
    assert boundary_edge_count(got.mesh.faces) == 0  # the blocks still meet


@pytest.mark.slow  # the whole CThead, blockwise
def test_blocks_hold_their_borders_and_half_the_bound(cthead) -> None:
    """After the blocks' own decimation (before the pass across them) the blocks still
    meet (the welded mesh is closed: their border vertices were held) and the mesh is
    within half the bound of the full surface, as the stage reports (not without the
    borders held: 30 mm off where blocks left holes)."""
    from miss.measure._jit import bound_check
    from miss.surface.blockwise import BlockDecimation, blockwise_decimated

    decimation = BlockDecimation("quadric", 0.9, 0.002)
    welded, stage = blockwise_decimated(cthead, 1500.0, decimation, block=40)
    full = blockwise_surface(cthead, 1500.0, normals=False, block=40)
    assert stage.triangles_in == full.n_triangles > stage.triangles_out == welded.n_triangles
    assert stage.diagonal_mm == pytest.approx(full.diagonal())
    assert stage.bound_mm == pytest.approx(0.001 * full.diagonal())
    exact = bound_check(full, _as_subset(full, welded))
    assert exact.max_mm <= stage.max_mm + 1e-6 * full.diagonal()
    assert stage.max_mm <= stage.bound_mm + 1e-6 * full.diagonal()
    assert boundary_edge_count(welded.faces) == 0


def test_a_label_map_on_disk_makes_the_model_it_makes_in_memory(tmp_path) -> None:
    """Label maps are not blockwise yet: a lazy one (stored, read by chunks) is read whole
    for the job, and the model is the in-memory one's, part by part."""
    from miss.pipeline import run
    from miss.server.storage import chunked
    from miss.spec import JobSpec

    labels = np.zeros((40, 36, 30), np.uint8, order="F")
    labels[3:15, 4:20, 5:25], labels[20:35, 10:30, 3:12], labels[22:30, 5:9, 15:28] = 1, 2, 7
    affine = np.diag([0.8, 0.9, 1.5, 1.0])
    chunked.write_array(tmp_path / "labels.zarr", labels, {"affine": affine.tolist()})
    lazy = Volume(chunked.open_array(tmp_path / "labels.zarr")[0], affine)
    spec = JobSpec.of(labels="all", decimate="none", formats=("glb",))
    got, want = run(lazy, spec, measure=False), run(Volume(labels, affine), spec, measure=False)
    assert [p.name for p in got.scene.parts] == [p.name for p in want.scene.parts]
    for a, b in zip(got.scene.parts, want.scene.parts, strict=True):
        np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
        np.testing.assert_array_equal(a.mesh.faces, b.mesh.faces)


def _random_block(rng: np.random.Generator, width: int):
    """A block of random vertices whose face vertices have few edge ids (so they repeat
    across blocks, and once in a while within the block); some blocks are empty."""
    from miss.surface.blocks import BlockMesh

    n = int(rng.integers(0, 40)) if rng.random() < 0.9 else 0
    shared = rng.choice(n, size=int(rng.integers(0, n + 1)), replace=False)
    keys = rng.integers(0, 25, size=len(shared)).astype(np.int64)
    if len(keys) > 1 and rng.random() < 0.2:
        keys[-1] = keys[0]  # a copy within the block itself
    faces = rng.integers(0, max(n, 1), size=(int(rng.integers(1, 60)) if n else 0, 3))
    return BlockMesh(
        vertices=rng.random((n, 3)).astype(np.float32),
        faces=faces.astype(np.int32),
        normals=rng.random((n, width)).astype(np.float32),
        shared=shared.astype(np.int64),
        keys=keys,
    )


def _weld_at_the_end(parts: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The weld as it was done before blocks were welded as they came: every block kept,
    then each edge id's first vertex (in arrival order) standing for all its copies."""
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts])
    shared = np.concatenate([p.shared + o for p, o in zip(parts, offsets, strict=False)])
    keys = np.concatenate([p.keys for p in parts])
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    to = shared[first][inverse]
    copies = to != shared
    keep = np.ones(offsets[-1], dtype=bool)
    keep[shared[copies]] = False
    number = np.cumsum(keep) - 1
    number[shared[copies]] = number[to[copies]]
    verts = np.concatenate([p.vertices for p in parts])[keep]
    normals = np.concatenate([p.normals for p in parts])[keep]
    faces = np.concatenate([number[p.faces + o] for p, o in zip(parts, offsets, strict=False)])
    return verts, faces.astype(np.int32), normals


def test_blocks_welded_as_they_come_equal_a_weld_at_the_end() -> None:
    """Random blocks whose face vertices share edge ids with earlier blocks' (and, once,
    with another vertex of their own block): the welder's mesh is the weld of all of them
    at the end, vertex for vertex, whatever order they come in; and welded as they come in
    a shuffled order but ``in_order``, the mesh of a weld in their own order, vertex for
    vertex and triangle for triangle, each shared vertex (and its normal) from the first
    block in that order that has it."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from miss.surface.blocks import Welder

    @settings(max_examples=80, deadline=None)
    @given(st.integers(0, 2**32 - 1), st.integers(1, 30), st.sampled_from([0, 3]))
    def check(seed: int, count: int, width: int) -> None:
        rng = np.random.default_rng(seed)
        parts = [_random_block(rng, width) for _ in range(count)]
        want = _weld_at_the_end(parts)
        welders = []
        for as_they_come in (True, False):
            welders.append(Welder(as_they_come))
            for part in parts:
                welders[-1].add(part, part.vertices, part.normals)
        welders.append(Welder(as_they_come=True, in_order=True))
        for i in rng.permutation(count):
            welders[-1].add(parts[i], parts[i].vertices, parts[i].normals, int(i))
        for welder in welders:
            verts, faces, normals = welder.result()
            assert np.array_equal(verts, want[0]) and np.array_equal(normals, want[2])
            assert np.array_equal(faces, want[1]) and faces.dtype == np.int32

    check()
    empty = Welder().result()
    assert [a.shape for a in empty] == [(0, 3), (0, 3), (0, 3)]


def test_the_same_volume_makes_the_same_mesh_every_time_on_threads(cthead) -> None:
    """Blocks made on threads are welded in the blocks' order, not in the order they end:
    the same vertices in the same order every run (the decimation after it, and so the
    model, depends on that order)."""
    runs = [
        blockwise_surface(cthead, 1500.0, normals=False, block=24, cluster=False) for _ in range(4)
    ]
    for other in runs[1:]:
        assert np.array_equal(other.vertices, runs[0].vertices)
        assert np.array_equal(other.faces, runs[0].faces)
