"""Wavefront OBJ text: ``v``, ``vn`` and ``f a//a b//b c//c`` (1-based indices).

Every 3-D tool imports it; it is the simplest format to inspect by eye. Vertex
and normal share an index because MISS stores one normal per vertex.

A scene is one OBJ: an ``o``/``g`` group per part. Colours would need a ``.mtl`` file
beside it, which one downloaded file cannot carry; each part's name, colour and
opacity are in a comment above its group instead (the PLY, glTF and 3MF files carry
colours that readers apply).
"""

from __future__ import annotations

import numpy as np

from miss.export._text import format_rows, utf8
from miss.geometry import mesh_normals
from miss.scene import Part, Scene, safe_names
from miss.types import Mesh


def write(mesh: Mesh, *, title: str | None = None, metadata: dict[str, str] | None = None) -> bytes:
    """Encode ``mesh`` as OBJ.

    Parameters
    ----------
    mesh : Mesh
        Vertices (N, 3) in LPS mm, faces (F, 3) counter-clockwise from outside
        (OBJ's front-face convention); normals computed when ``mesh.normals`` is None.
    title, metadata
        ``o title`` (the object name) and one ``# key: value`` comment each.

    Returns
    -------
    bytes
        UTF-8 text; coordinates to 3 decimals (um), normals to 4.
    """
    normals = mesh_normals(mesh)
    comments = [
        "MISS surface; units mm; axes patient LPS (+x left, +y posterior, +z superior)",
        *(f"{key}: {value}" for key, value in (metadata or {}).items()),
    ]
    head = "".join(f"# {' '.join(str(text).splitlines())}\n" for text in comments)
    if title:
        head += f"o {' '.join(title.split())}\n"  # a name is one line; keep it one word-run
    indices = mesh.faces[:, [0, 0, 1, 1, 2, 2]].astype(np.int64) + 1
    return b"".join(
        [
            utf8(head),
            format_rows(mesh.vertices, b"v {} {} {}\n", 3),
            format_rows(normals, b"vn {} {} {}\n", 4),
            format_rows(indices, b"f {}//{} {}//{} {}//{}\n"),
        ]
    )


def write_scene(
    scene: Scene, *, title: str | None = None, metadata: dict[str, str] | None = None
) -> bytes:
    """One OBJ with an ``o``/``g`` group per part (the part's name made one safe word),
    vertex indices running on across parts; above each group a comment with the part's
    full name, sRGB colour and opacity."""
    names = safe_names(scene.parts)
    comments = [
        "MISS scene; units mm; axes patient LPS (+x left, +y posterior, +z superior)",
        f"title: {title or scene.title}",
        *(f"{key}: {value}" for key, value in (metadata or {}).items()),
    ]
    body = [utf8("".join(f"# {' '.join(str(text).splitlines())}\n" for text in comments))]
    offset = 1  # OBJ indices are 1-based and global
    for part, key in zip(scene.parts, names, strict=True):
        mesh = part.mesh
        indices = mesh.faces[:, [0, 0, 1, 1, 2, 2]].astype(np.int64) + offset
        body += [
            utf8(_part_comment(part) + f"o {key}\ng {key}\n"),
            format_rows(mesh.vertices, b"v {} {} {}\n", 3),
            format_rows(mesh_normals(mesh), b"vn {} {} {}\n", 4),
            format_rows(indices, b"f {}//{} {}//{} {}//{}\n"),
        ]
        offset += mesh.n_vertices
    return b"".join(body)


def _part_comment(part: Part) -> str:
    """``# part: <name>; colour r g b (sRGB); opacity o[; label L]`` and a newline."""
    r, g, b = part.color
    label = "" if part.label is None else f"; label {part.label}"
    name = " ".join(part.name.split())
    return f"# part: {name}; colour {r:.4f} {g:.4f} {b:.4f} (sRGB); opacity {part.opacity:.4f}{label}\n"
