"""X3D XML encoding (ISO/IEC 19776-1), VRML's successor: the same scene as ``vrml``.

An ``IndexedTriangleSet`` rather than VRML's ``IndexedFaceSet``: every face is a
triangle, so the ``-1`` terminators would only cost bytes. Provenance goes into
``<head><meta>``. Millimetres and patient LPS as in ``vrml`` (X3D's nominal unit
is the metre; the ``units`` meta element says what the numbers are).

The document is assembled from strings rather than an element tree: the numeric
attributes are megabytes of digits that need no escaping, while titles and
metadata, the only free text, go through ``quoteattr``; characters XML 1.0 cannot hold
at all (C0 controls but tab and line ends, lone surrogates, U+FFFE and U+FFFF), which a
label table or a file name can bring, become U+FFFD rather than an unreadable document.
"""

from __future__ import annotations

from xml.sax.saxutils import quoteattr

import numpy as np

from miss.export._text import format_rows, xml_safe
from miss.export.vrml import BONE_RGB, DEFAULT_TITLE, viewpoint
from miss.geometry import mesh_normals
from miss.scene import Part, Scene, safe_names
from miss.types import Mesh

# Interchange is the smallest profile with IndexedTriangleSet and Viewpoint.
_OPENING = (
    '<?xml version="1.0" encoding="UTF-8"?>\n'
    '<X3D profile="Interchange" version="3.3"'
    ' xmlns:xsd="http://www.w3.org/2001/XMLSchema-instance"'
    ' xsd:noNamespaceSchemaLocation="http://www.web3d.org/specifications/x3d-3.3.xsd">\n'
)


def write(mesh: Mesh, *, title: str | None = None, metadata: dict[str, str] | None = None) -> bytes:
    """Encode ``mesh`` as an X3D ``.x3d`` XML document (the contract of every writer: ``miss.export``).

    ``title`` and ``metadata`` become ``<meta name="title">`` and one ``<meta name=key
    content=value>`` each. UTF-8 XML; coordinates to 3 decimals (um), normals to 4, one
    vertex or triangle per line inside the attribute values (XML reads newlines there as
    spaces).
    """
    opening = _OPENING + _head(title, metadata) + _scene_opening(mesh)
    return opening.encode("utf-8") + _triangle_set(mesh) + b"  </Scene>\n</X3D>\n"


def _head(title: str | None, metadata: dict[str, str] | None) -> str:
    """``<head>`` with title, units and one ``<meta>`` per provenance entry."""
    # A list, not a dict: a provenance key called "title" must not replace the title.
    entries = [
        ("title", title or DEFAULT_TITLE),
        ("generator", "MISS (Medical Image Sharing System)"),
        ("units", "millimetres; axes patient LPS (+x left, +y posterior, +z superior)"),
        *(metadata or {}).items(),
    ]
    metas = "".join(
        f"  <meta name={_attribute(key)} content={_attribute(value)}/>\n" for key, value in entries
    )
    return f" <head>\n{metas} </head>\n"


def _attribute(text: object) -> str:
    """``text`` quoted as an XML attribute value, U+FFFD for what XML cannot hold."""
    return quoteattr(xml_safe(text))


def _scene_opening(mesh: Mesh) -> str:
    """``<Scene>`` up to the geometry: navigation, front camera, bone material."""
    position, orientation = viewpoint(mesh)
    centre = " ".join(f"{c:.3f}" for c in mesh.bounds().mean(axis=0))
    r, g, b = BONE_RGB
    return (
        " <Scene>\n"
        '  <NavigationInfo type=\'"EXAMINE" "ANY"\'/>\n'
        f'  <Viewpoint description="Anterior" position="{position}"'
        f' orientation="{orientation}" centerOfRotation="{centre}"/>\n'
        "  <Shape>\n   <Appearance>\n"
        f'    <Material diffuseColor="{r} {g} {b}" specularColor="0.2 0.2 0.2" shininess="0.2"/>\n'
        "   </Appearance>\n"
    )


# ------------------------------------------------------------------ scenes


def write_scene(
    scene: Scene, *, title: str | None = None, metadata: dict[str, str] | None = None
) -> bytes:
    """Encode a :class:`~miss.scene.Scene` as X3D: one ``Shape`` per part.

    Each shape is ``DEF``-named after its part (a valid XML id) with a
    ``MetadataString name="part"`` holding the full name (and the label, when
    there is one); its ``Material`` has the part's colour and ``1 - opacity`` as
    ``transparency``. Title defaults to the scene's.
    """
    names = safe_names(scene.parts)
    bounds = Mesh(scene.bounds().astype(np.float32), np.zeros((0, 3), dtype=np.int32))
    position, orientation = viewpoint(bounds)
    centre = " ".join(f"{c:.3f}" for c in bounds.bounds().mean(axis=0))
    opening = (
        _OPENING
        + _head(title or scene.title, metadata)
        + " <Scene>\n"
        + '  <NavigationInfo type=\'"EXAMINE" "ANY"\'/>\n'
        + f'  <Viewpoint description="Anterior" position="{position}"'
        + f' orientation="{orientation}" centerOfRotation="{centre}"/>\n'
    )
    shapes = [_shape(part, key) for part, key in zip(scene.parts, names, strict=True)]
    return b"".join([opening.encode("utf-8"), *shapes, b" </Scene>\n</X3D>\n"])


def _shape(part: Part, key: str) -> bytes:
    """``<Shape DEF=key>`` with the part's name as metadata, its material and triangles."""
    names = [part.name] if part.label is None else [part.name, f"label {part.label}"]
    mfstring = " ".join('"' + n.replace("\\", "\\\\").replace('"', '\\"') + '"' for n in names)
    r, g, b = (f"{c:.4f}" for c in part.color)
    opening = (
        f'  <Shape DEF="{key}">\n'
        f'   <MetadataString containerField="metadata" name="part" value={_attribute(mfstring)}/>\n'
        "   <Appearance>\n"
        f'    <Material diffuseColor="{r} {g} {b}" specularColor="0.2 0.2 0.2" shininess="0.2"'
        f' transparency="{1.0 - part.opacity:.4f}"/>\n'
        "   </Appearance>\n"
    )
    return opening.encode("utf-8") + _triangle_set(part.mesh)


def _triangle_set(mesh: Mesh) -> bytes:
    """``<IndexedTriangleSet>`` with coordinates and normals, and the closing ``</Shape>``."""
    return b"".join(
        [
            b'    <IndexedTriangleSet solid="true" ccw="true" normalPerVertex="true" index="\n',
            format_rows(mesh.faces, b"{} {} {}\n"),
            b'">\n     <Coordinate point="\n',
            format_rows(mesh.vertices, b"{} {} {}\n", 3),
            b'"/>\n     <Normal vector="\n',
            format_rows(mesh_normals(mesh), b"{} {} {}\n", 4),
            b'"/>\n    </IndexedTriangleSet>\n   </Shape>\n',
        ]
    )
