"""Levels of detail (``miss.export.tiles``): an octree of simplified fragments as 3D Tiles.

Checked on the demo phantom's skin and bone as a scene of two coloured parts, undecimated
(about 300,000 triangles): every triangle is in exactly one leaf, at full resolution; the
root is far smaller; errors never grow with depth; a coarse fragment's border is the
full-resolution cut (no cracks against finer neighbours); tiles keep the parts' names and
colours and pass the Khronos glTF-Validator."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest
from test_gltf_validator import Validate, assert_valid
from test_gltf_validator import validate as validate  # the fixture, shared

from miss.demo import phantom
from miss.export.tiles import TILESET, TileNode, etag, plan, walk, write_tiles
from miss.pipeline import run
from miss.scene import Scene
from miss.spec import JobSpec

TILE = 4096


@pytest.fixture(scope="module")
def scene() -> Scene:
    spec = JobSpec.of(levels=[-500, 300], decimate="none", formats=("glb",))
    return run(phantom(), spec, measure=False).scene


@pytest.fixture(scope="module")
def root(scene: Scene) -> TileNode:
    return plan(scene, TILE)


def rows(faces: np.ndarray) -> np.ndarray:
    """Triangles as sorted rows, sorted: the same triangles compare equal in any order."""
    out = np.sort(np.asarray(faces, dtype=np.int64), axis=1)
    return out[np.lexsort(out.T[::-1])]


def test_every_triangle_is_in_exactly_one_leaf(scene: Scene, root: TileNode) -> None:
    leaves = [n for n in walk(root) if not n.children]
    assert len(leaves) > 8
    for i, part in enumerate(scene.parts):
        joined = np.concatenate([leaf.fragment[i] for leaf in leaves])
        assert len(joined) == part.mesh.n_triangles
        np.testing.assert_array_equal(rows(joined), rows(part.mesh.faces))
    assert all(sum(len(f) for f in leaf.fragment) <= TILE for leaf in leaves)


def test_root_is_far_smaller_and_errors_fall_with_depth(scene: Scene, root: TileNode) -> None:
    assert sum(len(f) for f in root.fragment) <= 1.1 * TILE < scene.n_triangles / 20
    assert root.error > 0
    for node in walk(root):
        for child in node.children:
            assert child.error <= node.error
        if not node.children:
            assert node.error == 0.0
    # the simplification error is a fraction of the model, not of a voxel: visible far away
    assert root.error < 0.05 * scene.diagonal()


def border_edges(faces: np.ndarray) -> set[tuple[int, int]]:
    """Edges of one triangle only (undirected)."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return {tuple(e) for e in unique[counts == 1].tolist()}


def test_coarse_fragments_keep_their_borders(scene: Scene, root: TileNode) -> None:
    """A simplified fragment's border is its full-resolution triangles' border: it meets a
    neighbour drawn at any level without a crack."""
    inner = [n for n in walk(root) if n.children and n is not root]
    assert inner
    for node in inner:
        for i, part in enumerate(scene.parts):
            full = part.mesh.faces[node.members[i]]
            if len(full):
                assert border_edges(node.fragment[i]) == border_edges(full)


def test_tileset_json(scene: Scene) -> None:
    files = write_tiles(scene, tile_triangles=TILE)
    tileset = json.loads(files[TILESET])
    assert tileset["asset"]["version"] == "1.1"
    assert tileset["root"]["refine"] == "REPLACE"
    tiles: list[dict[str, Any]] = []

    def visit(tile: dict[str, Any], parent: dict[str, Any] | None) -> None:
        tiles.append(tile)
        assert tile["content"]["uri"] in files
        if parent is not None:
            assert tile["geometricError"] <= parent["geometricError"]
        for child in tile.get("children", []):
            visit(child, tile)

    visit(tileset["root"], None)
    assert tileset["geometricError"] > tileset["root"]["geometricError"] > 0
    assert len(files) == len(tiles) + 1
    center = np.array(tileset["root"]["boundingVolume"]["box"][:3])
    half = np.diag(np.reshape(tileset["root"]["boundingVolume"]["box"][3:], (3, 3)))
    lo, hi = scene.bounds() / 1000
    np.testing.assert_allclose(center - half, lo, atol=1e-6)
    np.testing.assert_allclose(center + half, hi, atol=1e-6)
    assert etag(files) != etag({**files, TILESET: b"{}"})


def glb_json(glb: bytes) -> dict[str, Any]:
    """The JSON chunk of a GLB (after the 12-byte header and the chunk's 8)."""
    length = int.from_bytes(glb[12:16], "little")
    return dict(json.loads(glb[20 : 20 + length]))


def test_tiles_keep_parts_and_pass_the_validator(scene: Scene, validate: Validate) -> None:
    files = write_tiles(scene, tile_triangles=TILE)
    plain = write_tiles(scene, tile_triangles=TILE, compress=False)
    materials = glb_json(files["tiles/r.glb"])["materials"]
    assert [m["name"] for m in materials] == [p.name for p in scene.parts]
    assert len({tuple(m["pbrMetallicRoughness"]["baseColorFactor"]) for m in materials}) == 2
    leaf = max((n for n in plain if n.count("/") and len(n) > len("tiles/r.glb")), key=len)
    assert_valid(
        validate(
            {"root": files["tiles/r.glb"], "root-plain": plain["tiles/r.glb"], "leaf": plain[leaf]}
        )
    )


class Recorder:
    """A sink that notes what it gets, in order."""

    wants_preview = False

    def __init__(self, lod_triangles: int | None) -> None:
        self.lod_triangles = lod_triangles
        self.got: list[str] = []
        self.lod: dict[str, bytes] = {}

    def put(self, fmt: str, data: bytes) -> None:
        self.got.append(fmt)

    def put_lod(self, files: Any) -> None:
        self.got.append("lod")
        self.lod = dict(files)

    def deliver(self, result: Any) -> None:
        return None


def test_the_job_writes_levels_of_detail_before_the_glb_when_over_budget() -> None:
    spec = JobSpec.of(level=300, sample_rate=2, decimate="none", formats=("stl", "glb", "wrl"))
    over, within = Recorder(5_000), Recorder(10_000_000)
    result = run(phantom(), spec, sink=over, measure=False)
    assert result.scene.n_triangles > 5_000
    assert over.got == ["lod", "glb", "stl", "wrl"] and TILESET in over.lod
    assert "lod" in result.seconds
    run(phantom(), spec, sink=within, measure=False)
    assert within.got == ["glb", "stl", "wrl"]
