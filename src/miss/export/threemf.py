"""3MF (3D Manufacturing Format, core specification 1.3): what 3-D printing labs ask for.

A 3MF file is an OPC package, a zip of three entries: ``[Content_Types].xml``,
``_rels/.rels`` (pointing at the model) and ``3D/3dmodel.model``, the XML model. The
model says ``unit="millimeter"``; the numbers are MISS's patient LPS millimetres
untouched. LPS is right-handed (left x posterior = superior) like 3MF's space, and
MISS winds faces counter-clockwise from outside, which is 3MF's rule too, so neither
coordinates nor winding change: normals point out. Slicers place the model on their
plate themselves; its position in the patient is kept for anyone who overlays it.

Colours come from the core specification alone (no extension to support): one
``<basematerials>`` group with a ``<base>`` per part, ``displaycolor`` its sRGB colour
and its opacity as the alpha (``#RRGGBBAA``); each part is one ``<object>`` with its
name and that material, and the ``<build>`` has one item per part. Title and provenance
are ``<metadata>``: ``Title`` and ``Application`` are the specification's own names,
each provenance entry is ``miss:<key>`` in a namespace of ours, as the specification
asks of names it does not define.

3MF forbids a triangle with a repeated vertex index; such triangles enclose nothing and
are left out. Coordinates are written to 3 decimals (um). The package is byte-for-byte
reproducible (fixed zip timestamps, see ``_zip``).
"""

from __future__ import annotations

import re
from xml.sax.saxutils import escape, quoteattr

from miss.export._text import format_rows, utf8, xml_safe
from miss.export._zip import zip_files
from miss.export.vrml import BONE_RGB, DEFAULT_TITLE
from miss.scene import Part, Scene
from miss.types import Mesh

MODEL_PATH = "3D/3dmodel.model"
CORE_NAMESPACE = "http://schemas.microsoft.com/3dmanufacturing/core/2015/02"
#: The namespace of MISS's own metadata names (provenance).
MISS_NAMESPACE = "urn:miss:3mf:provenance"

_CONTENT_TYPES = (
    '<?xml version="1.0" encoding="UTF-8"?>\n'
    '<Types xmlns="http://schemas.openxmlformats.org/package/2006/content-types">\n'
    ' <Default Extension="rels"'
    ' ContentType="application/vnd.openxmlformats-package.relationships+xml"/>\n'
    ' <Default Extension="model"'
    ' ContentType="application/vnd.ms-package.3dmanufacturing-3dmodel+xml"/>\n'
    "</Types>\n"
).encode("ascii")
_RELATIONSHIPS = (
    '<?xml version="1.0" encoding="UTF-8"?>\n'
    '<Relationships xmlns="http://schemas.openxmlformats.org/package/2006/relationships">\n'
    f' <Relationship Id="rel0" Target="/{MODEL_PATH}"'
    ' Type="http://schemas.microsoft.com/3dmanufacturing/2013/01/3dmodel"/>\n'
    "</Relationships>\n"
).encode("ascii")

# What an XML name may not contain (a metadata key becomes the local part of a QName).
_NOT_NAME = re.compile(r"[^A-Za-z0-9_.-]")


def write(mesh: Mesh, *, title: str | None = None, metadata: dict[str, str] | None = None) -> bytes:
    """Encode ``mesh`` as a 3MF package (the contract of every writer: ``miss.export``).

    One object, bone-coloured, named ``title``; ``metadata`` becomes ``miss:<key>``
    metadata. Vertices (N, 3) in mm, faces (F, 3) counter-clockwise from outside.
    """
    name = title or DEFAULT_TITLE
    return _package([Part(name, mesh, BONE_RGB)], name, metadata)


def write_scene(
    scene: Scene, *, title: str | None = None, metadata: dict[str, str] | None = None
) -> bytes:
    """Encode a :class:`~miss.scene.Scene` as one 3MF package: an object per part, each
    with its name and a base material of its colour and opacity (alpha). Title defaults
    to the scene's."""
    return _package(list(scene.parts), title or scene.title, metadata)


def _package(parts: list[Part], title: str, metadata: dict[str, str] | None) -> bytes:
    """The three OPC entries around the model document."""
    return zip_files(
        [
            ("[Content_Types].xml", _CONTENT_TYPES),
            ("_rels/.rels", _RELATIONSHIPS),
            (MODEL_PATH, _model(parts, title, metadata)),
        ]
    )


def _model(parts: list[Part], title: str, metadata: dict[str, str] | None) -> bytes:
    """``3D/3dmodel.model``: metadata, the materials, one object per part, the build."""
    opening = (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        f'<model unit="millimeter" xml:lang="en-US" xmlns="{CORE_NAMESPACE}"'
        f' xmlns:miss="{MISS_NAMESPACE}">\n'
        + _metadata(title, metadata)
        + " <resources>\n"
        + _materials(parts)
    )
    objects = [_object(part, 2 + index, index) for index, part in enumerate(parts)]
    items = "".join(f'  <item objectid="{2 + index}"/>\n' for index in range(len(parts)))
    closing = f" </resources>\n <build>\n{items} </build>\n</model>\n"
    return b"".join([utf8(opening), *objects, closing.encode("ascii")])


def _metadata(title: str, metadata: dict[str, str] | None) -> str:
    """``Title``, ``Application`` and one ``miss:<key>`` per provenance entry (names unique,
    as 3MF requires: a key that is not an XML name is made one, a repeat numbered)."""
    entries = {"Title": title, "Application": "MISS (Medical Image Sharing System)"}
    for key, value in (metadata or {}).items():
        name = "miss:" + (_NOT_NAME.sub("_", str(key)).lstrip(".-0123456789") or "_")
        unique, count = name, 1
        while unique in entries:
            count += 1
            unique = f"{name}_{count}"
        entries[unique] = value
    return "".join(
        f" <metadata name={quoteattr(name)}>{escape(xml_safe(value))}</metadata>\n"
        for name, value in entries.items()
    )


def _materials(parts: list[Part]) -> str:
    """One ``<basematerials id="1">`` with a ``<base>`` per part: its name and colour."""
    bases = "".join(
        f'   <base name={quoteattr(xml_safe(part.name))} displaycolor="{_colour(part)}"/>\n'
        for part in parts
    )
    return f'  <basematerials id="1">\n{bases}  </basematerials>\n'


def _colour(part: Part) -> str:
    """``#RRGGBBAA``: sRGB and opacity as alpha, 8 bits each."""
    channels = (*part.color, part.opacity)
    return "#" + "".join(f"{round(255 * c):02X}" for c in channels)


def _object(part: Part, object_id: int, material: int) -> bytes:
    """``<object>`` with the part's mesh; triangles with a repeated index are left out."""
    faces = part.mesh.faces
    distinct = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
    distinct &= faces[:, 0] != faces[:, 2]
    opening = (
        f'  <object id="{object_id}" type="model" name={quoteattr(xml_safe(part.name))}'
        f' pid="1" pindex="{material}">\n   <mesh>\n    <vertices>\n'
    )
    return b"".join(
        [
            utf8(opening),
            format_rows(part.mesh.vertices, b'<vertex x="{}" y="{}" z="{}"/>\n', 3),
            b"    </vertices>\n    <triangles>\n",
            format_rows(faces[distinct], b'<triangle v1="{}" v2="{}" v3="{}"/>\n'),
            b"    </triangles>\n   </mesh>\n  </object>\n",
        ]
    )
