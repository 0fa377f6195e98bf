"""Wavefront OBJ text: ``v``, ``vn`` and ``f a//a b//b c//c`` (1-based indices).

Every 3-D tool imports it; it is the simplest format to inspect by eye. Vertex
and normal share an index because MISS stores one normal per vertex.
"""

from __future__ import annotations

import numpy as np

from miss.export._text import format_rows, utf8
from miss.export._zip import manifest, zip_files
from miss.geometry import mesh_normals
from miss.scene import Scene, safe_names
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
    """A zip of ``scene.obj``, its ``scene.mtl`` and ``scene.json``.

    One ``o``/``usemtl`` group per part (the part's name made one safe word),
    vertex indices running on across parts. The MTL gives each part ``Kd`` (its
    sRGB colour) and ``d`` (its opacity).
    """
    names = safe_names(scene.parts)
    comments = [
        "MISS scene; units mm; axes patient LPS (+x left, +y posterior, +z superior)",
        f"title: {title or scene.title}",
        *(f"{key}: {value}" for key, value in (metadata or {}).items()),
    ]
    head = "".join(f"# {' '.join(str(text).splitlines())}\n" for text in comments)
    body = [utf8(head + "mtllib scene.mtl\n")]
    offset = 1  # OBJ indices are 1-based and global
    for part, key in zip(scene.parts, names, strict=True):
        mesh = part.mesh
        normals = mesh_normals(mesh)
        indices = mesh.faces[:, [0, 0, 1, 1, 2, 2]].astype(np.int64) + offset
        body += [
            f"o {key}\nusemtl {key}\n".encode(),
            format_rows(mesh.vertices, b"v {} {} {}\n", 3),
            format_rows(normals, b"vn {} {} {}\n", 4),
            format_rows(indices, b"f {}//{} {}//{} {}//{}\n"),
        ]
        offset += mesh.n_vertices
    listing = manifest(scene, ["scene.obj"] * len(names), title, metadata)
    return zip_files(
        [("scene.obj", b"".join(body)), ("scene.mtl", _mtl(scene, names)), ("scene.json", listing)]
    )


def _mtl(scene: Scene, names: list[str]) -> bytes:
    """One ``newmtl`` per part: diffuse colour ``Kd`` and dissolve ``d`` (opacity)."""
    blocks = [
        f"newmtl {key}\nKa 0 0 0\nKd {part.color[0]:.4f} {part.color[1]:.4f} {part.color[2]:.4f}\n"
        f"Ks 0.2 0.2 0.2\nNs 20\nd {part.opacity:.4f}\nillum 2\n"
        for part, key in zip(scene.parts, names, strict=True)
    ]
    return utf8("# MISS scene materials\n" + "\n".join(blocks))
