"""A level's components block by block (:mod:`miss.structures.block_components`): the same
pieces, choice, notes and surfaces as the in-memory path, on CThead from Zarr at several
block sizes, and a piece that crosses the blocks' seams only at their corners."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_blocks import FLOAT32_ROUNDING_MM, assert_same_surface

from miss.io import load_volume
from miss.pipeline import STAGE_SPANS, run
from miss.server.storage import chunked
from miss.spec import JobSpec
from miss.structures.block_components import blockwise_components
from miss.structures.build import _component_meshes
from miss.structures.components import select_components
from miss.surface.blockwise import BlockRun
from miss.types import Volume

LEVEL = 1500.0


@pytest.fixture(scope="module")
def cthead(datasets: Path) -> Volume:
    return load_volume(datasets / "ct_head_stanford_cthead" / "CThead.nhdr")


@pytest.fixture(scope="module")
def lazy_cthead(cthead: Volume, tmp_path_factory: pytest.TempPathFactory) -> Volume:
    """CThead as the server stores it: chunked Zarr, read lazily."""
    path = tmp_path_factory.mktemp("zarr") / "cthead.zarr"
    chunked.write_array(path, cthead.data, {"affine": cthead.affine.tolist()})
    voxels, affine, _ = chunked.open_array(path)
    return Volume(voxels, affine, cthead.meta)


def _item(**form: object):
    return JobSpec.of(level=LEVEL, **form).structures.items[0]


def _same_parts(lazy: Volume, memory: Volume, block: object, **form: object) -> list[str]:
    """Both paths' meshes for one level's components, compared part by part; the notes."""
    item = _item(**form)
    want_notes: list[str] = []
    want = _component_meshes(memory, item, want_notes, "bone")
    notes: list[str] = []
    got = _component_meshes(lazy, item, notes, "bone", BlockRun(block=block))
    assert len(got) == len(want)
    for mesh, reference in zip(got, want, strict=True):
        assert_same_surface(mesh, reference, FLOAT32_ROUNDING_MM)
    assert notes == want_notes
    return notes


@pytest.mark.parametrize("block", [24, (50, 37, 29)])
@pytest.mark.slow
def test_cthead_largest_and_split_equal_the_in_memory_path(cthead, lazy_cthead, block) -> None:
    notes = _same_parts(lazy_cthead, cthead, block, components="largest")
    assert notes == ["bone: 125 smaller piece(s) left out"]
    notes = _same_parts(lazy_cthead, cthead, block, components="split", max_parts=3)
    assert notes == ["bone: 123 smaller piece(s) left out"]


def test_cthead_min_size_drops_the_same_pieces(cthead, lazy_cthead) -> None:
    voxel_mm3 = abs(float(np.linalg.det(cthead.affine[:3, :3])))
    wanted = select_components(cthead.data > LEVEL, "split", 40, 16)
    assert len(wanted.kept) == 3  # 335014, 73 and 43 voxels: the rest are under 40
    notes = _same_parts(
        lazy_cthead, cthead, 32, components="split", max_parts=16, min_size_mm3=40 * voxel_mm3
    )
    assert notes == ["bone: 123 smaller piece(s) left out"]


def test_a_job_s_region_of_a_lazy_volume_equals_the_in_memory_one(cthead, lazy_cthead) -> None:
    """A sampled, cropped region of data on disk is a StridedView: its components too."""
    spec = JobSpec.of(
        level=LEVEL, components="split", max_parts=3, sample_rate=2, roi=(10, 240, 20, 230, 5, 100)
    )
    lazy, memory = spec.region.apply(lazy_cthead), spec.region.apply(cthead)
    assert type(lazy.data).__name__ == "StridedView"
    item = spec.structures.items[0]
    got = _component_meshes(lazy, item, [], "bone", BlockRun(block=(20, 30, 17)))
    want = _component_meshes(memory, item, [], "bone")
    assert len(got) == len(want) == 3
    for mesh, reference in zip(got, want, strict=True):
        assert_same_surface(mesh, reference, FLOAT32_ROUNDING_MM)


def test_blockwise_choice_is_ndimage_s_ids_and_sizes(cthead, lazy_cthead) -> None:
    """Every component, numbered as ndimage.label numbers them (ties broken alike)."""
    wanted = select_components(cthead.data > LEVEL, "split", 0, 1000)
    chosen = blockwise_components(lazy_cthead, LEVEL, "split", 0, 1000, block=(50, 37, 29))
    assert [g[0] for g in chosen.groups] == wanted.kept
    assert chosen.sizes == wanted.sizes
    assert chosen.dropped == wanted.dropped == 0


def _snake(size: int = 40) -> Volume:
    """A chain of voxels along the main diagonal (each touches the next at a corner only),
    then back along a face diagonal (edges only), and a small blob apart: two pieces."""
    data = np.zeros((size, size, size), dtype=np.int16, order="F")
    for i in range(size):
        data[i, i, i] = 100
    for i in range(size - 1):
        data[size - 1 - i, size - 2 - i, size - 1] = 100
    data[2:5, 30:33, 5:8] = 100  # 27 voxels, far from both chains
    return Volume(data, np.diag([0.7, 0.8, 1.1, 1.0]), {})


def test_a_piece_that_crosses_the_seams_only_at_corners_is_one(tmp_path) -> None:
    snake = _snake()
    want = select_components(snake.data > 50, "split", 0, 10)
    assert want.sizes == [79, 27]  # the two chains meet at (39, 39, 39) and (39, 38, 39)
    for block in (4, 5, (3, 7, 2)):
        chosen = blockwise_components(snake, 50.0, "split", 0, 10, block=block)
        assert chosen.sizes == want.sizes and [g[0] for g in chosen.groups] == want.kept
    path = tmp_path / "snake.zarr"
    chunked.write_array(path, snake.data, {"affine": snake.affine.tolist()})
    voxels, affine, _ = chunked.open_array(path)
    lazy = Volume(voxels, affine, {})
    item = JobSpec.of(level=50.0, components="largest").structures.items[0]
    notes: list[str] = []
    (got,) = _component_meshes(lazy, item, notes, "snake", BlockRun(block=4))
    (want_mesh,) = _component_meshes(snake, item, [], "snake")
    assert_same_surface(got, want_mesh, FLOAT32_ROUNDING_MM)
    assert notes == ["snake: 1 smaller piece(s) left out"]


def test_a_job_on_a_lazy_volume_keeps_its_largest_piece(cthead, lazy_cthead) -> None:
    """The reproduction: '>' on a StridedView crashed the job."""
    spec = JobSpec.of(level=LEVEL, components="largest", formats=("glb",))
    seen: list[tuple[str, float]] = []
    result = run(lazy_cthead, spec, measure=False, progress=lambda s, f: seen.append((s, f)))
    assert result.artifacts["glb"][:4] == b"glTF"
    # the job's fraction (``pipeline.STAGE_SPANS``): surface runs from its start to its end
    start, end = STAGE_SPANS["surface"]
    surface = [f for stage, f in seen if stage == "surface"]
    assert surface == sorted(surface) and surface[-1] == pytest.approx(end)
    labelling = start + 0.3 * (end - start)  # the labelling counted too
    assert any(start < f < labelling for f in surface)
    assert any(n.endswith(": 125 smaller piece(s) left out") for n in result.scene.notes)
    assert len(result.scene.parts) == 1


@pytest.mark.slow  # a local Dask cluster
def test_on_a_dask_cluster_the_same_as_on_threads(tmp_path) -> None:
    """The tasks and their items pickle: both passes on one local cluster, the snake read
    from Zarr by the workers."""
    from miss.structures.block_components import component_surfaces
    from miss.surface.runner import local_cluster

    snake = _snake()
    path = tmp_path / "snake.zarr"
    chunked.write_array(path, snake.data, {"affine": snake.affine.tolist()})
    voxels, affine, _ = chunked.open_array(path)
    lazy = Volume(voxels, affine, {})
    threads = blockwise_components(lazy, 50.0, "split", 0, 10, block=8)
    want = component_surfaces(lazy, 50.0, threads)
    with local_cluster(2) as cluster:
        address = cluster.scheduler_address
        chosen = blockwise_components(lazy, 50.0, "split", 0, 10, block=8, scheduler=address)
        got = component_surfaces(lazy, 50.0, chosen, scheduler=address)
    assert chosen.sizes == threads.sizes == [79, 27]
    for mesh, reference in zip(got, want, strict=True):
        assert_same_surface(mesh, reference, 0.0)
