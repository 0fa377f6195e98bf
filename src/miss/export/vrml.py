"""VRML 2.0 (VRML97, ISO/IEC 14772-1): the format the 1998 MISS served.

One ``Shape`` with an ``IndexedFaceSet`` carrying per-vertex normals, so the
browser need not compute them (the paper's point), a ``WorldInfo`` with the
provenance and a ``Viewpoint`` that frames the model from the front.

Units: VRML97 nominally measures length in metres, but MISS writes patient
millimetres exactly as the 1998 system did (browsers fit the view to whatever
scale they get, and 3 decimals of a millimetre is the scanner's precision,
1 um). A reader wanting metres multiplies by 0.001. Axes are patient LPS:
+x left, +y posterior, +z superior.
"""

from __future__ import annotations

import gzip
import math

import numpy as np

from miss.export._text import format_rows, utf8
from miss.geometry import mesh_normals
from miss.scene import Part, Scene, safe_names
from miss.types import Mesh

# Bone: 3D Slicer's generic-anatomy "bone" (241, 214, 145) as sRGB fractions.
BONE_RGB = (0.945, 0.839, 0.569)

DEFAULT_TITLE = "MISS surface model"


def write(mesh: Mesh, *, title: str | None = None, metadata: dict[str, str] | None = None) -> bytes:
    """Encode ``mesh`` as a VRML 2.0 ``.wrl`` file (the contract of every writer: ``miss.export``).

    ``title`` and ``metadata`` become ``WorldInfo.title`` and ``WorldInfo.info`` (one
    ``"key: value"`` string each). UTF-8 text; coordinates to 3 decimals (um), normals
    to 4. Data rows are not indented and use commas only as row ends: size is what the
    network pays.
    """
    normals = mesh_normals(mesh)
    return b"".join(
        [
            utf8(_header(mesh, title, metadata)),
            _face_set_rows(mesh, normals),
        ]
    )


def _header(mesh: Mesh, title: str | None, metadata: dict[str, str] | None) -> str:
    """Everything up to the first coordinate: provenance, camera, material."""
    info = " ".join(_sf_string(f"{key}: {value}") for key, value in (metadata or {}).items())
    position, orientation = viewpoint(mesh)
    r, g, b = BONE_RGB
    return (
        "#VRML V2.0 utf8\n"
        "# Written by MISS. Units: millimetres (not VRML's nominal metres); axes: patient LPS.\n"
        f"WorldInfo {{\n  title {_sf_string(title or DEFAULT_TITLE)}\n  info [ {info} ]\n}}\n"
        'NavigationInfo { type [ "EXAMINE", "ANY" ] }\n'
        f'Viewpoint {{ description "Anterior" position {position} orientation {orientation} }}\n'
        "Shape {\n  appearance Appearance {\n    material Material {\n"
        f"      diffuseColor {r} {g} {b}\n      specularColor 0.2 0.2 0.2\n      shininess 0.2\n"
        "    }\n  }\n  geometry IndexedFaceSet {\n    solid TRUE\n    ccw TRUE\n"
        "    normalPerVertex TRUE\n    coord Coordinate { point [\n"
    )


def write_gzip(
    mesh: Mesh, *, title: str | None = None, metadata: dict[str, str] | None = None
) -> bytes:
    """``.wrz``: the ``.wrl`` bytes gzipped, which every VRML97 browser must accept.

    The gzip header's mtime is 0 so the same mesh always gives the same bytes
    (cacheable, comparable by hash). Level 6, zlib's default: on a 63 MB file
    level 9 took 2.8x as long for 0.4 % less, level 1 a fifth of the time for 23 % more.
    """
    return gzip.compress(write(mesh, title=title, metadata=metadata), compresslevel=6, mtime=0)


def viewpoint(mesh: Mesh) -> tuple[str, str]:
    """VRML/X3D ``position`` and ``orientation`` that show the whole mesh from the front.

    The default camera looks down -z with +y up; a +90 degree turn about x makes
    it look along +y (posterior, so from in front of the patient) with +z
    (superior) up. The distance fits the bounding sphere in the default
    45 degree field of view.
    """
    lo, hi = mesh.bounds().astype(np.float64)
    centre = (lo + hi) / 2
    distance = max(mesh.diagonal(), 1.0) / 2 / math.tan(math.pi / 8) * 1.1
    x, y, z = centre[0], centre[1] - distance, centre[2]
    return f"{x:.3f} {y:.3f} {z:.3f}", f"1 0 0 {math.pi / 2:.6f}"


def _sf_string(text: str) -> str:
    r"""A VRML SFString literal: double quotes, with ``"`` and ``\`` backslash-escaped."""
    return '"' + str(text).replace("\\", "\\\\").replace('"', '\\"') + '"'


# ------------------------------------------------------------------ scenes


def write_scene(
    scene: Scene, *, title: str | None = None, metadata: dict[str, str] | None = None
) -> bytes:
    """Encode a :class:`~miss.scene.Scene` as VRML 2.0: one ``Shape`` per part.

    Each shape is ``DEF``-named after its part (made a valid VRML name: letters,
    digits, ``_``) and carries its colour as ``Material.diffuseColor`` and
    ``1 - opacity`` as ``transparency``. The full names go into
    ``WorldInfo.info`` as ``"part <DEF>: <name>"`` and into a comment before each
    shape. Title defaults to the scene's; one ``Viewpoint`` frames all parts.
    """
    names = safe_names(scene.parts)
    parts_info = {f"part {key}": part.name for key, part in zip(names, scene.parts, strict=True)}
    head = _scene_header(scene, title or scene.title, {**(metadata or {}), **parts_info})
    return b"".join(
        [utf8(head)] + [_shape(part, key) for part, key in zip(scene.parts, names, strict=True)]
    )


def write_scene_gzip(
    scene: Scene, *, title: str | None = None, metadata: dict[str, str] | None = None
) -> bytes:
    """``.wrz`` of a scene: :func:`write_scene` gzipped (mtime 0, level 6 as :func:`write_gzip`)."""
    data = write_scene(scene, title=title, metadata=metadata)
    return gzip.compress(data, compresslevel=6, mtime=0)


def _scene_header(scene: Scene, title: str, metadata: dict[str, str]) -> str:
    """Header, provenance, navigation and one camera framing every part."""
    info = " ".join(_sf_string(f"{key}: {value}") for key, value in metadata.items())
    position, orientation = viewpoint(Mesh(scene.bounds().astype(np.float32), _NO_FACES))
    return (
        "#VRML V2.0 utf8\n"
        "# Written by MISS. Units: millimetres (not VRML's nominal metres); axes: patient LPS.\n"
        f"WorldInfo {{\n  title {_sf_string(title)}\n  info [ {info} ]\n}}\n"
        'NavigationInfo { type [ "EXAMINE", "ANY" ] }\n'
        f'Viewpoint {{ description "Anterior" position {position} orientation {orientation} }}\n'
    )


_NO_FACES = np.zeros((0, 3), dtype=np.int32)


def _shape(part: Part, key: str) -> bytes:
    """One part as ``DEF key Shape``: material with its colour and transparency, geometry."""
    mesh = part.mesh
    normals = mesh_normals(mesh)
    r, g, b = (f"{c:.4f}" for c in part.color)
    label = f" (label {part.label})" if part.label is not None else ""
    comment = " ".join(f"{part.name}{label}".splitlines())
    opening = (
        f"# {comment}\nDEF {key} Shape {{\n  appearance Appearance {{\n    material Material {{\n"
        f"      diffuseColor {r} {g} {b}\n      specularColor 0.2 0.2 0.2\n      shininess 0.2\n"
        f"      transparency {1.0 - part.opacity:.4f}\n    }}\n  }}\n"
        "  geometry IndexedFaceSet {\n    solid TRUE\n    ccw TRUE\n"
        "    normalPerVertex TRUE\n    coord Coordinate { point [\n"
    )
    return utf8(opening) + _face_set_rows(mesh, normals)


def _face_set_rows(mesh: Mesh, normals: np.ndarray) -> bytes:
    """The data rows of an ``IndexedFaceSet`` opened by the caller, and its closing brackets."""
    return b"".join(
        [
            format_rows(mesh.vertices, b"{} {} {},\n", 3),
            b"    ] }\n    normal Normal { vector [\n",
            format_rows(normals, b"{} {} {},\n", 4),
            b"    ] }\n    coordIndex [\n",
            format_rows(mesh.faces, b"{} {} {} -1,\n"),
            b"    ]\n  }\n}\n",
        ]
    )
