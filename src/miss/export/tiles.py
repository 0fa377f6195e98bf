"""Levels of detail: a large scene as an OGC 3D Tiles 1.1 tileset of compressed glTF tiles.

Why 3D Tiles rather than neuroglancer's precomputed multi-resolution meshes: it is an
open standard (OGC) whose tiles are plain glTF, so every tile is the GLB MISS already
writes (meshopt-compressed, parts named and coloured) and passes the Khronos
validator; the tree is a readable ``tileset.json``; CesiumJS, NASA's
``3d-tiles-renderer`` and other viewers open it. Neuroglancer's format is a custom
binary (Draco fragments in a manifest) only neuroglancer reads.

The tree. An octree over the scene's bounding cube: a node holding more than
``tile_triangles`` triangles (by centroid) splits into its occupied octants. Leaves keep
their triangles at full resolution. A node above them holds its children's triangles
simplified (meshoptimizer, quadric) to about ``tile_triangles``, the vertices on the
fragment's border locked: every fragment's border is the full-resolution cut through
the mesh, so a coarse tile meets its neighbour's finer tiles without cracks. A tile's
``geometricError`` (metres, as 3D Tiles asks) is its simplification error plus its
children's largest: it never grows with depth; leaves have 0. ``refine: REPLACE``.

Frames. Each tile is a GLB as :func:`miss.export.gltf.write_scene` writes it (root node
LPS mm to glTF's Y-up metres); a 3D Tiles runtime turns glTF's Y-up into the tileset's
Z-up, which makes the tileset frame patient LPS in metres: bounding boxes are LPS m.
Each tile's ``extras.triangles`` tells a viewer what drawing it costs before loading it.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import meshoptimizer
import numpy as np

from miss._process import usable_cores
from miss.errors import EmptySurface
from miss.export.gltf import write_scene
from miss.geometry import mesh_normals
from miss.scene import Part, Scene
from miss.types import Mesh

#: Triangles a tile holds, about: leaves at most this, inner tiles simplified to it.
TILE_TRIANGLES = 32_768
#: Deepest octree level: a cube of 1/2^8 the model's size (about 1 mm for a head).
MAX_DEPTH = 8
TILESET = "tileset.json"
_LOCK = meshoptimizer.SIMPLIFY_LOCK_BORDER | meshoptimizer.SIMPLIFY_SPARSE
_ABSOLUTE = meshoptimizer.SIMPLIFY_ERROR_ABSOLUTE


@dataclass
class TileNode:
    """One octree node: its key ("r", "r0", "r07" ...), its triangles per part (indices into
    that part's faces) and, once built, its fragment (faces per part) and error in mm."""

    key: str
    lo: np.ndarray  # (3,) mm, the cube's low corner
    size: float  # mm, the cube's side
    members: list[np.ndarray]  # per part, indices of the faces whose centroid is inside
    children: list[TileNode] = field(default_factory=list)
    fragment: list[np.ndarray] = field(default_factory=list)  # per part, (F, 3) faces
    error: float = 0.0

    @property
    def n_members(self) -> int:
        """Faces inside this tile, over all parts."""
        return sum(len(m) for m in self.members)


def write_tiles(
    scene: Scene,
    *,
    title: str | None = None,
    metadata: dict[str, str] | None = None,
    tile_triangles: int = TILE_TRIANGLES,
    compress: bool = True,
) -> dict[str, bytes]:
    """Encode ``scene`` as a 3D Tiles 1.1 tileset.

    Parameters
    ----------
    scene : Scene
        Parts with vertices (N, 3) in LPS mm and faces (F, 3).
    title, metadata
        As for the GLB writer; each tile carries them.
    tile_triangles : int
        About how many triangles a tile holds (leaves at most, inner tiles simplified
        to it).
    compress : bool
        Tiles with EXT_meshopt_compression (as the server sends them).

    Returns
    -------
    dict of str to bytes
        ``tileset.json`` and ``tiles/<key>.glb`` (the root is ``tiles/r.glb``), relative
        names; the caller decides where they go.
    """
    root = plan(scene, tile_triangles)
    normals = [mesh_normals(p.mesh) for p in scene.parts]  # shared: no seams between tiles

    def encode(node: TileNode) -> bytes:
        parts = [
            Part(p.name, _compact(p.mesh.vertices, n, faces), p.color, p.opacity, p.label)
            for p, faces, n in zip(scene.parts, node.fragment, normals, strict=True)
            if len(faces)
        ]
        tile = Scene(tuple(parts), title=scene.title)
        return write_scene(tile, title=title, metadata=metadata, compress=compress)

    nodes = walk(root)
    with ThreadPoolExecutor(_threads(), thread_name_prefix="miss-tiles") as pool:
        encoded = list(pool.map(encode, nodes))  # meshoptimizer's calls leave the GIL
    files = {f"tiles/{node.key}.glb": data for node, data in zip(nodes, encoded, strict=True)}
    files[TILESET] = json.dumps(_tileset(root, scene), indent=1).encode()
    return files


def _threads() -> int:
    """Threads for the tiles' simplification and encoding: the cores this process may use,
    at most four (each tile is the same bytes however many there are)."""
    return min(4, usable_cores())


def plan(scene: Scene, tile_triangles: int = TILE_TRIANGLES) -> TileNode:
    """The octree of ``scene`` with every node's fragment and error (mm) filled in."""
    if scene.n_triangles == 0:
        raise EmptySurface("Nothing to tile: the scene has no triangles.")
    tile_triangles = max(64, int(tile_triangles))
    root = _octree(scene, tile_triangles)
    _simplify(root, scene, tile_triangles)
    return root


def etag(files: Mapping[str, bytes]) -> str:
    """One tag for a whole tileset: changes when any of its files does."""
    digest = hashlib.sha256()
    for name in sorted(files):
        digest.update(name.encode() + b"\0" + hashlib.sha256(files[name]).digest())
    return digest.hexdigest()[:32]


def _compact(vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray) -> Mesh:
    """The vertices (and normals) ``faces`` use, faces renumbered: a tile's writer then
    works on the tile, not on the whole model's vertex arrays."""
    used, inverse = np.unique(faces, return_inverse=True)
    return Mesh(vertices[used], inverse.reshape(-1, 3).astype(np.int32), normals=normals[used])


def walk(node: TileNode) -> list[TileNode]:
    """The node and all below it, parents first."""
    out = [node]
    for child in node.children:
        out += walk(child)
    return out


def _octree(scene: Scene, tile_triangles: int) -> TileNode:
    """Split the bounding cube until no node holds more than ``tile_triangles``."""
    centroids = [p.mesh.vertices[p.mesh.faces].mean(axis=1) for p in scene.parts]
    lo, hi = scene.bounds()
    size = float((hi - lo).max()) * (1 + 1e-6) or 1.0
    root = TileNode("r", lo.astype(np.float64), size, [np.arange(len(c)) for c in centroids])
    todo = [root]
    while todo:
        node = todo.pop()
        if node.n_members <= tile_triangles or len(node.key) > MAX_DEPTH:
            continue
        half = node.size / 2
        octants = [
            ((c[m] - node.lo) >= half).astype(int) @ np.array([1, 2, 4])
            for c, m in zip(centroids, node.members, strict=True)
        ]
        for i in range(8):
            members = [m[o == i] for m, o in zip(node.members, octants, strict=True)]
            if sum(len(m) for m in members):
                offset = np.array([i & 1, (i >> 1) & 1, (i >> 2) & 1]) * half
                node.children.append(TileNode(f"{node.key}{i}", node.lo + offset, half, members))
        todo += node.children
    return root


def _simplify(root: TileNode, scene: Scene, tile_triangles: int) -> None:
    """Fill each node's fragment, the deepest nodes first, the nodes of one depth on
    several threads (each needs only its children's): a leaf keeps its faces, a parent
    simplifies its children's fragments together, its border locked."""
    depths: list[list[TileNode]] = []
    level = [root]
    while level:
        depths.append(level)
        level = [child for node in level for child in node.children]
    with ThreadPoolExecutor(_threads(), thread_name_prefix="miss-tiles") as pool:
        for nodes in reversed(depths):
            list(pool.map(lambda node: _fill(node, scene, tile_triangles), nodes))


def _fill(node: TileNode, scene: Scene, tile_triangles: int) -> None:
    """One node's fragment and error, its children's filled in already."""
    if not node.children:
        node.fragment = [p.mesh.faces[m] for p, m in zip(scene.parts, node.members, strict=True)]
        return
    joined = [
        np.concatenate([c.fragment[i] for c in node.children]) for i in range(len(scene.parts))
    ]
    total = sum(len(f) for f in joined)
    errors = []
    node.fragment = []
    for part, faces in zip(scene.parts, joined, strict=True):
        target = int(np.ceil(len(faces) * tile_triangles / total))
        simplified, error = _simplified(part.mesh.vertices, faces, target, node.size)
        node.fragment.append(simplified)
        errors.append(error)
    node.error = max(errors) + max(c.error for c in node.children)


def _simplified(
    vertices: np.ndarray, faces: np.ndarray, target: int, size: float
) -> tuple[np.ndarray, float]:
    """``faces`` (F, 3) simplified towards ``target`` triangles, border vertices kept;
    returns the faces and the error reached in mm (0 for none)."""
    if len(faces) <= target:
        return faces, 0.0
    indices = np.ascontiguousarray(faces, dtype=np.uint32).ravel()
    out = np.zeros_like(indices)
    error = np.zeros(1, dtype=np.float32)
    positions = np.ascontiguousarray(vertices, dtype=np.float32)
    n = meshoptimizer.simplify(
        out, indices, positions, target_index_count=3 * target, target_error=size,
        options=_LOCK | _ABSOLUTE, result_error=error,
    )  # fmt: skip
    return out[:n].reshape(-1, 3).astype(faces.dtype), float(error[0])


def _tileset(root: TileNode, scene: Scene) -> dict[str, Any]:
    """The tileset.json document: asset, root geometric error, the tile tree."""
    return {
        "asset": {"version": "1.1", "generator": "MISS (Medical Image Sharing System)"},
        "extras": {"frame": "patient LPS, metres", "triangles": scene.n_triangles},
        "geometricError": scene.diagonal() / 1000,
        "root": {**_tile(root, scene), "refine": "REPLACE"},
    }


def _tile(node: TileNode, scene: Scene) -> dict[str, Any]:
    """One tile: bounding box of all its triangles at full resolution (LPS m), error (m),
    content, triangle count, children."""
    children = [_tile(c, scene) for c in node.children]
    if children:  # the union of the children's boxes: each triangle is read once, in a leaf
        corners = np.array([_corners(c["boundingVolume"]["box"]) for c in children])
        lo, hi = corners[:, 0].min(axis=0), corners[:, 1].max(axis=0)
    else:
        used = [
            p.mesh.vertices[p.mesh.faces[m].ravel()]
            for p, m in zip(scene.parts, node.members, strict=True)
            if len(m)
        ]
        points = np.concatenate(used).astype(np.float64) / 1000
        lo, hi = points.min(axis=0), points.max(axis=0)
    center, half = (lo + hi) / 2, (hi - lo) / 2
    box = [*center, half[0], 0, 0, 0, half[1], 0, 0, 0, half[2]]
    tile: dict[str, Any] = {
        "boundingVolume": {"box": [float(x) for x in box]},
        "geometricError": node.error / 1000,
        "content": {"uri": f"tiles/{node.key}.glb"},
        "extras": {"triangles": sum(len(f) for f in node.fragment)},
    }
    if children:
        tile["children"] = children
    return tile


def _corners(box: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned 3D Tiles box's low and high corners."""
    center, half = np.array(box[:3]), np.array([box[3], box[7], box[11]])
    return center - half, center + half
