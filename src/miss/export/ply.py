"""PLY (Stanford polygon format), binary little-endian, with per-vertex normals.

Meshlab, CloudCompare and Blender read it; it keeps the shared-vertex structure
STL throws away. Provenance goes into ``comment`` header lines.
"""

from __future__ import annotations

import numpy as np

from miss.export._zip import zip_parts
from miss.geometry import mesh_normals
from miss.scene import Scene
from miss.types import Mesh

# "<": the header says binary_little_endian, so the body is little-endian on any host.
_VERTEX_NAMES = ("x", "y", "z", "nx", "ny", "nz")
_VERTEX = np.dtype([(name, "<f4") for name in _VERTEX_NAMES])
# A PLY list property: uchar count (always 3) then three int indices; packed, 13 bytes.
_FACE = np.dtype([("count", "u1"), ("indices", "<i4", (3,))])


def write(mesh: Mesh, *, title: str | None = None, metadata: dict[str, str] | None = None) -> bytes:
    """Encode ``mesh`` as binary little-endian PLY (the contract of every writer: ``miss.export``).

    ``title`` and ``metadata`` become ``comment title: ...`` and one ``comment key: value``
    line each. An ASCII header, then 24 N + 13 F bytes.
    """
    normals = mesh_normals(mesh)
    vertices = np.empty(mesh.n_vertices, dtype=_VERTEX)  # every field is written below
    for axis, name in enumerate("xyz"):
        vertices[name] = mesh.vertices[:, axis]
        vertices["n" + name] = normals[:, axis]
    faces = np.empty(mesh.n_triangles, dtype=_FACE)
    faces["count"] = 3
    faces["indices"] = mesh.faces
    return _header(mesh, title, metadata) + vertices.tobytes() + faces.tobytes()


def _header(mesh: Mesh, title: str | None, metadata: dict[str, str] | None) -> bytes:
    """The ASCII header: format, provenance comments, element and property declarations."""
    comments = [
        "MISS surface; units mm; axes patient LPS (+x left, +y posterior, +z superior)",
        *([f"title: {title}"] if title else []),
        *(f"{key}: {value}" for key, value in (metadata or {}).items()),
    ]
    lines = [
        "ply",
        "format binary_little_endian 1.0",
        *(f"comment {_one_line(text)}" for text in comments),
        f"element vertex {mesh.n_vertices}",
        *(f"property float {name}" for name in _VERTEX_NAMES),
        f"element face {mesh.n_triangles}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    # The header is ASCII by definition: anything else is escaped, not dropped.
    return ("\n".join(lines) + "\n").encode("ascii", "backslashreplace")


def _one_line(text: str) -> str:
    """A header line ends at the first newline, so fold line breaks into spaces."""
    return " ".join(str(text).splitlines())


def write_scene(
    scene: Scene, *, title: str | None = None, metadata: dict[str, str] | None = None
) -> bytes:
    """A zip of one binary PLY per part (``01_<name>.ply`` ...) and ``scene.json``.

    Each PLY's title comment is its part's name; colours are in the manifest.
    """
    return zip_parts(scene, write, "ply", title, metadata)
