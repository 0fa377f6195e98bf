"""Every VRML file MISS writes is read without a single warning by a VRML 2.0 implementation
that is not ours, and holds what MISS meant to write. VRML's classic encoding has no schema;
the reader is Castle Game Engine's ``tovrmlx3d`` (Debian's ``view3dscene``, installed by
``make test``), which reports whatever it cannot parse or place (an unknown node or field,
a value of the wrong type, a node in a field that cannot hold it, an unclosed bracket) as a
warning and stops reading there. It writes the scene it read as X3D XML, and that is read
back here: every triangle (degenerate ones too), vertex, normal count, colour, opacity and
part name. Cases as in test_gltf_validator.py and test_x3d_schema.py; ``.wrz`` as well."""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Callable

import numpy as np
import pytest
from lxml import etree

import miss
from miss.demo import phantom
from miss.export import WRITERS, export
from miss.export.vrml import BONE_RGB
from miss.pipeline import run
from miss.scene import Part, Scene, safe_names
from miss.spec import JobSpec

COORD_TOL = 0.0005 + 1e-5  # 3 decimals of a mm, then float32 in the reader
TITLE = 'Skull "CT" <bone> & more \\ back'
METADATA = {"level": "1500 HU", "note": 'quote " back\\slash # not a comment\nnew line'}

Read = Callable[[str, bytes], etree._Element]


@pytest.fixture(scope="module")
def castle(tmp_path_factory: pytest.TempPathFactory) -> Read:
    """``castle(file_name, data)`` -> the scene tovrmlx3d read, as its X3D XML root."""
    tool = shutil.which("tovrmlx3d")
    if tool is None:
        pytest.skip("tovrmlx3d is not installed: run `make test` (Debian's view3dscene)")
    folder = tmp_path_factory.mktemp("vrml")

    def read(file_name: str, data: bytes) -> etree._Element:
        path = folder / file_name
        path.write_bytes(data)
        out = subprocess.run(
            [tool, str(path), "--encoding=xml"], capture_output=True, timeout=300, check=False
        )
        assert (out.returncode, out.stderr.decode()) == (0, ""), file_name
        parser = etree.XMLParser(no_network=True, resolve_entities=False, huge_tree=True)
        return etree.fromstring(out.stdout, parser)

    return read


def wrl(mesh_or_scene: miss.Mesh | Scene, fmt: str = "wrl", **options: object) -> bytes:
    writer = WRITERS[fmt]
    write = writer.write_scene if isinstance(mesh_or_scene, Scene) else writer.write
    return write(mesh_or_scene, **options)


def numbers(element: etree._Element, attribute: str, dtype: type, width: int) -> np.ndarray:
    return np.array(element.get(attribute, "").split(), dtype=dtype).reshape(-1, width)


def assert_holds(root: etree._Element, parts: list[Part], names: list[str] | None) -> None:
    """The read scene has one shape per part with its triangles, material and name."""
    shapes = root.findall("Scene/Shape")
    assert len(shapes) == len(parts)
    for shape, part, name in zip(shapes, parts, names or [None] * len(parts), strict=True):
        faces = shape.find("IndexedFaceSet")
        index = numbers(faces, "coordIndex", np.int64, 4)
        assert (index[:, 3] == -1).all()
        np.testing.assert_array_equal(index[:, :3], part.mesh.faces)
        points = numbers(faces.find("Coordinate"), "point", np.float64, 3)
        np.testing.assert_allclose(points, part.mesh.vertices, rtol=0, atol=COORD_TOL)
        assert len(numbers(faces.find("Normal"), "vector", np.float64, 3)) == len(points)
        material = shape.find("Appearance/Material")
        colour = numbers(material, "diffuseColor", np.float64, 3)[0]
        np.testing.assert_allclose(colour, part.color, atol=5e-5)
        transparency = float(material.get("transparency", "0"))  # Castle omits the default
        assert transparency == pytest.approx(1.0 - part.opacity, abs=5e-5)
        assert shape.get("DEF") == name


def assert_mesh(root: etree._Element, mesh: miss.Mesh) -> None:
    assert_holds(root, [Part("surface", mesh, BONE_RGB)], None)


def assert_scene(root: etree._Element, scene: Scene) -> None:
    assert_holds(root, list(scene.parts), safe_names(scene.parts))
    info = root.find("Scene/WorldInfo").get("info")
    for part in scene.parts:
        assert part.name.replace("\\", "\\\\").replace('"', '\\"') in info


def test_phantom_and_degenerate_meshes(castle: Read, degenerate_mesh: miss.Mesh) -> None:
    surface = miss.extract_surface(phantom(), 300.0, sample_rate=2)
    decimated = miss.decimate(surface, reduce=0.9, measure=False)[0]
    zero = miss.Mesh(
        degenerate_mesh.vertices, degenerate_mesh.faces, normals=np.zeros((6, 3), np.float32)
    )
    for name, mesh in [("bone", surface), ("decimated", decimated), ("degenerate", zero)]:
        assert_mesh(castle(f"{name}.wrl", wrl(mesh)), mesh)
    assert_mesh(castle("bone.wrz", wrl(surface, "wrz")), surface)
    titled = castle("titled.wrl", wrl(degenerate_mesh, title=TITLE, metadata=METADATA))
    world = titled.find("Scene/WorldInfo")
    assert world.get("title") == TITLE
    assert "level: 1500 HU" in world.get("info")


def test_phantom_scenes_split_and_layered(castle: Read, degenerate_mesh: miss.Mesh) -> None:
    volume = phantom()
    split = run(volume, JobSpec.of(level=300, components="split", sample_rate=2, formats=("wrl",)))
    layered = run(volume, JobSpec.of(levels=[-500, 300], sample_rate=2, formats=("wrz",)))
    assert len(split.scene.parts) > 1 and len(layered.scene.parts) == 2
    assert_scene(castle("split.wrl", split.artifacts["wrl"]), split.scene)
    assert_scene(castle("layered.wrz", layered.artifacts["wrz"]), layered.scene)
    names = Scene(
        (
            Part("Bone & skull", degenerate_mesh, (1.0, 0.5, 0.0), 0.35, label=3),
            Part("Bone & skull", degenerate_mesh, (0.0, 0.0, 0.0), 1.0),
            Part('3 "quoted" \\ name\nsecond line', degenerate_mesh, (1.0, 1.0, 1.0), 0.01),
            Part("Schädel", degenerate_mesh, (0.2, 0.4, 0.6), 0.5, label=70000),
        ),
        title=TITLE,
    )
    assert_scene(castle("names.wrl", wrl(names, metadata=METADATA)), names)


def test_the_reader_is_strict(castle: Read, degenerate_mesh: miss.Mesh) -> None:
    """What a hand-broken file makes tovrmlx3d say, so a clean read means something."""
    good = wrl(degenerate_mesh)
    broken = {
        "unknown-field": good.replace(b"ccw TRUE", b"clockwise TRUE"),
        "unknown-node": good.replace(b"Viewpoint {", b"Camera {"),
        "xml-boolean": good.replace(b"solid TRUE", b"solid true"),
        "two-numbers": good.replace(b"9.000 9.000 9.000,", b"9.000 9.000,"),
        "wrong-field": good.replace(b"material Material", b"material Coordinate"),
    }
    for name, data in broken.items():
        assert data != good
        with pytest.raises(AssertionError, match=name):
            castle(f"{name}.wrl", data)


def test_real_scans(castle: Read, real_scenes: dict[str, Scene]) -> None:
    bone, labels = real_scenes["cthead-bone"], real_scenes["frog-labels"]
    assert len(labels.parts) > 20
    assert_scene(castle("cthead-bone.wrz", export(bone, "wrz")), bone)
    assert_scene(castle("frog-labels.wrl", export(labels, "wrl")), labels)
