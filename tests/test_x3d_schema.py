"""Every X3D file MISS writes is valid against the Web3D Consortium's X3D XML Schema of the
version the file declares (x3d-3.3.xsd and the two extension files it includes, vendored
unmodified in tests/validators/x3d with their licence), checked by lxml (libxml2) with no
network: the schema's includes resolve to the files beside it, and the test checks that
nothing else was asked for. Cases as in test_gltf_validator.py: the demo phantom, a mesh
with degenerate triangles, split and layered scenes with names, colours and opacity,
titles and provenance with characters XML must escape or cannot hold, and the real scans
(CThead bone, the frog's label map). Hand-broken documents are rejected, so the check
cannot pass on a schema that accepts anything."""

from __future__ import annotations

import re
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from lxml import etree

import miss
from miss.demo import phantom
from miss.export import WRITERS, export
from miss.pipeline import run
from miss.scene import Part, Scene
from miss.spec import JobSpec

SCHEMAS = Path(__file__).resolve().parent / "validators" / "x3d"
XSI = "http://www.w3.org/2001/XMLSchema-instance"
# Where the X3D specification publishes each version's schema; MISS names it in every file.
LOCATION = re.compile(r"https?://www\.web3d\.org/specifications/(x3d-(\d\.\d)\.xsd)")

TITLE = 'Skull "CT" <bone> & more'
METADATA = {"level": "1500 HU", "note": "quote \" apostrophe ' back\\slash\nnew line\ttab"}


class LocalFiles(etree.Resolver):
    """Records every document libxml2 asks for while the schema compiles (it loads them
    itself from the paths it names, and ``no_network`` stops any http fetch)."""

    def __init__(self) -> None:
        super().__init__()
        self.asked: list[str] = []

    def resolve(self, url: str | None, pubid: str | None, context: object) -> None:
        self.asked.append(str(url))


@cache
def schema(file_name: str) -> tuple[etree.XMLSchema, tuple[str, ...]]:
    """The vendored schema ``file_name`` compiled, and the documents that took."""
    path = SCHEMAS / file_name
    assert path.is_file(), f"{file_name} is not vendored in {SCHEMAS}"
    resolver = LocalFiles()
    parser = etree.XMLParser(no_network=True, resolve_entities=False)
    parser.resolvers.add(resolver)
    compiled = etree.XMLSchema(etree.parse(str(path), parser))
    return compiled, tuple(resolver.asked)


def validate(data: bytes) -> list[str]:
    """Schema errors of one X3D document (empty when valid), against the schema it declares.

    ``huge_tree`` lifts libxml2's 10 MB cap on one attribute value, a safety limit rather
    than a rule of XML: a CT bone's ``index`` attribute is longer than that.
    """
    parser = etree.XMLParser(no_network=True, resolve_entities=False, huge_tree=True)
    root = etree.fromstring(data, parser)  # raises if the bytes are not well-formed XML
    location = LOCATION.fullmatch(root.get(f"{{{XSI}}}noNamespaceSchemaLocation", ""))
    assert location, "the X3D element must name its schema (xsd:noNamespaceSchemaLocation)"
    assert location[2] == root.get("version"), "declared version and schema differ"
    compiled, _ = schema(location[1])
    compiled.validate(root)
    return [f"line {e.line}: {e.message}" for e in compiled.error_log]


def assert_valid(files: dict[str, bytes]) -> None:
    errors = {name: validate(data)[:5] for name, data in files.items()}
    assert errors == dict.fromkeys(files, [])


def x3d(mesh_or_scene: miss.Mesh | Scene, **options: object) -> bytes:
    writer = WRITERS["x3d"]
    write = writer.write_scene if isinstance(mesh_or_scene, Scene) else writer.write
    return write(mesh_or_scene, **options)


# ---------------------------------------------------------------- the check itself


def test_the_schema_compiles_from_the_vendored_files_only() -> None:
    _, asked = schema("x3d-3.3.xsd")
    names = sorted(Path(url).name for url in asked)
    assert all(Path(url).parent == SCHEMAS for url in asked), asked
    assert names == [
        "x3d-3.3-Web3dExtensionsPrivate.xsd",
        "x3d-3.3-Web3dExtensionsPublic.xsd",
        "x3d-3.3.xsd",
    ]
    licence = (SCHEMAS / "license.txt").read_text()
    assert "Web3D Consortium" in licence and "Redistribution and use" in licence


def test_miss_declares_the_version_it_is_validated_against(degenerate_mesh: miss.Mesh) -> None:
    root = etree.fromstring(x3d(degenerate_mesh))
    assert (root.get("version"), root.get("profile")) == ("3.3", "Interchange")
    location = root.get(f"{{{XSI}}}noNamespaceSchemaLocation")
    assert location == "http://www.web3d.org/specifications/x3d-3.3.xsd"


BROKEN = {
    "an element X3D does not have": (b"IndexedTriangleSet", b"IndexedTriangleSoup"),
    "an attribute it does not have": (b' ccw="true"', b' clockwise="true"'),
    "a node where it cannot go": (b"   <Appearance>", b"   <Viewpoint/><Appearance>"),
    "a boolean in VRML's spelling": (b'solid="true"', b'solid="TRUE"'),
    "a coordinate that is not a number": (b'point="\n', b'point="\nnan nan nan\n'),
    "a transparency above one": (b'transparency="0.0000"', b'transparency="1.5000"'),
    "an unknown profile": (b'profile="Interchange"', b'profile="Medical"'),
    "a DEF that is not an XML name": (b'<Shape DEF="bone_300_HU"', b'<Shape DEF="300 HU"'),
}


@pytest.mark.parametrize("case", BROKEN)
def test_a_broken_document_is_rejected(case: str) -> None:
    bone = miss.extract_surface(phantom(64, 3.0), 300.0)
    good = x3d(Scene((Part("bone (300 HU)", bone),)))
    old, new = BROKEN[case]
    assert old in good
    assert validate(good) == []
    assert validate(good.replace(old, new)), case


def test_the_schema_holds_the_declared_version(degenerate_mesh: miss.Mesh) -> None:
    """A file saying X3D 4.0 fails the 3.3 schema: the version picks the schema that counts."""
    compiled, _ = schema("x3d-3.3.xsd")
    root = etree.fromstring(x3d(degenerate_mesh).replace(b'version="3.3"', b'version="4.0"'))
    assert not compiled.validate(root)
    assert "version" in str(compiled.error_log)


# ---------------------------------------------------------------- what MISS writes


def test_phantom_and_degenerate_meshes(degenerate_mesh: miss.Mesh) -> None:
    surface = miss.extract_surface(phantom(), 300.0, sample_rate=2)
    decimated = miss.decimate(surface, reduce=0.9, measure=False)[0]
    zero = miss.Mesh(
        degenerate_mesh.vertices, degenerate_mesh.faces, normals=np.zeros((6, 3), np.float32)
    )
    assert_valid(
        {
            "bone": x3d(surface),
            "bone-titled": x3d(surface, title=TITLE, metadata=METADATA),
            "bone-decimated": x3d(decimated),
            "degenerate": x3d(degenerate_mesh),
            "zero-normals": x3d(zero),
        }
    )


def test_phantom_scenes_split_and_layered() -> None:
    volume = phantom()
    split = run(volume, JobSpec.of(level=300, components="split", sample_rate=2, formats=("x3d",)))
    layered = run(volume, JobSpec.of(levels=[-500, 300], sample_rate=2, formats=("x3d",)))
    assert len(split.scene.parts) > 1 and len(layered.scene.parts) == 2
    opacities = {part.opacity for part in layered.scene.parts}
    assert len(opacities) == 2  # skin see-through over opaque bone
    assert_valid(
        {
            "split": x3d(split.scene),
            "layered": x3d(layered.scene, title=TITLE, metadata=METADATA),
            "pipeline": layered.artifacts["x3d"],  # what the pipeline itself wrote
        }
    )


def test_part_names_that_clash_or_are_no_xml_names(degenerate_mesh: miss.Mesh) -> None:
    parts = (
        Part("Bone & skull", degenerate_mesh, (1.0, 0.5, 0.0), 0.35, label=3),
        Part("Bone & skull", degenerate_mesh, (0.0, 0.0, 0.0), 1.0),
        Part('3 "quoted" \\ name', degenerate_mesh, (1.0, 1.0, 1.0), 0.01),
        Part("Schädel", degenerate_mesh, (0.2, 0.4, 0.6), 0.5, label=70000),
    )
    assert_valid({"names": x3d(Scene(parts, title="<scene>"), metadata=METADATA)})


@pytest.mark.slow
def test_real_scans(real_scenes: dict[str, Scene]) -> None:
    assert len(real_scenes["frog-labels"].parts) > 20
    files = {name: export(scene, "x3d") for name, scene in real_scenes.items()}
    files["cthead-bone-mesh"] = export(real_scenes["cthead-bone"].parts[0].mesh, "x3d", title=TITLE)
    assert_valid(files)


def test_text_xml_cannot_hold_becomes_a_replacement_character(degenerate_mesh: miss.Mesh) -> None:
    """Controls from a label table or a DICOM text field, a file name's non-UTF-8 byte (a lone
    surrogate once Python decodes it): each becomes U+FFFD, the rest of the text stays."""
    title = "CT\x00head \x1b[1mbone\x1b[0m \udcff.nii"
    metadata = {"series\x0c": "description\x01", "ok": "tab\tnew line\n\x7f kept"}
    part = Part("femur\x0b left", degenerate_mesh, label=7)
    files = {
        "mesh": x3d(degenerate_mesh, title=title, metadata=metadata),
        "scene": x3d(Scene((part,), title=title), metadata=metadata),
    }
    assert_valid(files)
    root = etree.fromstring(files["scene"])
    metas = {m.get("name"): m.get("content") for m in root.iter("meta")}
    assert metas["title"] == "CT\ufffdhead \ufffd[1mbone\ufffd[0m \ufffd.nii"
    assert metas["series\ufffd"] == "description\ufffd"
    assert metas["ok"] == metadata["ok"]
    assert root.find(".//MetadataString").get("value") == '"femur\ufffd left" "label 7"'
