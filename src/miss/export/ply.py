"""PLY (Stanford polygon format), binary little-endian, with per-vertex normals.

Meshlab, CloudCompare and Blender read it; it keeps the shared-vertex structure
STL throws away. Provenance goes into ``comment`` header lines.

A scene is one PLY too: every part's vertices and faces in part order (indices running
on), each face coloured by its part (``red green blue alpha`` uchar face properties, the
sRGB colour and the opacity, which MeshLab, CloudCompare and trimesh read), and one
``comment part i: name, faces a..b`` line a part so that the parts can be split again.
"""

from __future__ import annotations

import numpy as np

from miss.geometry import mesh_normals
from miss.scene import Scene
from miss.types import Mesh

# "<": the header says binary_little_endian, so the body is little-endian on any host.
_VERTEX_NAMES = ("x", "y", "z", "nx", "ny", "nz")
_VERTEX = np.dtype([(name, "<f4") for name in _VERTEX_NAMES])
# A PLY list property: uchar count (always 3) then three int indices; packed, 13 bytes.
_FACE = np.dtype([("count", "u1"), ("indices", "<i4", (3,))])
# A scene's faces: the same, then the part's sRGB colour and opacity as uchar; 17 bytes.
_COLOURS = ("red", "green", "blue", "alpha")
_COLOURED_FACE = np.dtype(_FACE.descr + [(name, "u1") for name in _COLOURS])


def write(mesh: Mesh, *, title: str | None = None, metadata: dict[str, str] | None = None) -> bytes:
    """Encode ``mesh`` as binary little-endian PLY (the contract of every writer: ``miss.export``).

    ``title`` and ``metadata`` become ``comment title: ...`` and one ``comment key: value``
    line each. An ASCII header, then 24 N + 13 F bytes.
    """
    faces = np.empty(mesh.n_triangles, dtype=_FACE)  # every field is written below
    faces["count"] = 3
    faces["indices"] = mesh.faces
    head = _header(mesh.n_vertices, mesh.n_triangles, _comments(title, metadata), ())
    return head + _vertices(mesh.vertices, mesh_normals(mesh)).tobytes() + faces.tobytes()


def _vertices(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """The vertex element: (N,) records of position (mm) and unit normal, float32."""
    vertices = np.empty(len(points), dtype=_VERTEX)  # every field is written below
    for axis, name in enumerate("xyz"):
        vertices[name] = points[:, axis]
        vertices["n" + name] = normals[:, axis]
    return vertices


def _comments(title: str | None, metadata: dict[str, str] | None) -> list[str]:
    """The frame, the title and the provenance, one comment each."""
    return [
        "MISS surface; units mm; axes patient LPS (+x left, +y posterior, +z superior)",
        *([f"title: {title}"] if title else []),
        *(f"{key}: {value}" for key, value in (metadata or {}).items()),
    ]


def _header(
    n_vertices: int, n_faces: int, comments: list[str], face_properties: tuple[str, ...]
) -> bytes:
    """The ASCII header: format, comments, element and property declarations
    (``face_properties``: uchar ones after the indices)."""
    lines = [
        "ply",
        "format binary_little_endian 1.0",
        *(f"comment {_one_line(text)}" for text in comments),
        f"element vertex {n_vertices}",
        *(f"property float {name}" for name in _VERTEX_NAMES),
        f"element face {n_faces}",
        "property list uchar int vertex_indices",
        *(f"property uchar {name}" for name in face_properties),
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
    """One binary PLY of every part: vertices with normals, faces coloured by part.

    Each face's ``red green blue`` is its part's sRGB colour and ``alpha`` its opacity
    (0-255); a ``comment part i: <name>, faces a..b, label L`` line names each part's
    faces (0-based, inclusive).
    """
    merged = scene.merged()
    normals = np.concatenate([mesh_normals(part.mesh) for part in scene.parts])
    faces = np.empty(merged.n_triangles, dtype=_COLOURED_FACE)  # every field written below
    faces["count"] = 3
    faces["indices"] = merged.faces
    colours = np.array([[*part.color, part.opacity] for part in scene.parts])
    for channel, name in enumerate(_COLOURS):
        faces[name] = np.rint(colours[merged.labels, channel] * 255)
    comments = _comments(title or scene.title, metadata) + _part_comments(scene)
    head = _header(merged.n_vertices, merged.n_triangles, comments, _COLOURS)
    return head + _vertices(merged.vertices, normals).tobytes() + faces.tobytes()


def _part_comments(scene: Scene) -> list[str]:
    """``part i: name, faces a..b[, label L]`` per part, 1-based i, 0-based faces."""
    lines, start = [], 0
    for i, part in enumerate(scene.parts, start=1):
        end = start + part.mesh.n_triangles
        label = "" if part.label is None else f", label {part.label}"
        lines.append(f"part {i}: {part.name}, faces {start}..{end - 1}{label}")
        start = end
    return lines
