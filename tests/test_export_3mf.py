"""3MF read back by readers that are not ours: lib3mf (the 3MF Consortium's reference
library, in strict mode) and trimesh's 3MF loader. Triangles, millimetres, each part's
colour and opacity, closed and outward-wound where the input was; ``miss convert``.

No 3MF XML schema ships in an installed package, so the document is checked by lib3mf's
strict reading rather than against the XSD."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import zipfile
from pathlib import Path

import lib3mf
import numpy as np
import pytest
import trimesh

from miss.export import WRITERS, export
from miss.export.threemf import MODEL_PATH
from miss.export.vrml import BONE_RGB
from miss.scene import Part, Scene
from miss.types import Mesh

COORD_TOL = 0.0005 + 1e-4  # 3 decimals of a mm, plus float32 at a few hundred mm
METADATA = {"software": "MISS 0.1.0", "level (HU)": "95.5", "note": 'quote " & <tag>'}


def _mesh(tm: trimesh.Trimesh) -> Mesh:
    return Mesh(tm.vertices.astype(np.float32), tm.faces.astype(np.int32))


@pytest.fixture(scope="module")
def sphere() -> Mesh:
    """Icosphere of radius 80 mm centred at (-120, 35.5, 1002) mm, 1280 triangles."""
    tm = trimesh.creation.icosphere(subdivisions=3, radius=80.0)
    tm.apply_translation([-120.0, 35.5, 1002.0])
    return _mesh(tm)


@pytest.fixture(scope="module")
def scene(sphere: Mesh) -> Scene:
    """Translucent skin over a bone box and an open sheet (not closed, so not claimed so)."""
    box = trimesh.creation.box((10.0, 20.0, 30.0))
    sheet = Mesh(np.array([[0, 0, 0], [5, 0, 0], [0, 5, 0]], np.float32), np.array([[0, 1, 2]]))
    return Scene(
        (
            Part("skin & <scalp>", sphere, (0.9, 0.7, 0.6), opacity=0.4, label=1),
            Part("bone", _mesh(box), (1.0, 1.0, 0.0), label=2),
            Part("cut", sheet, (0.0, 0.2, 1.0)),
        ),
        title="Head",
    )


def read_lib3mf(data: bytes) -> lib3mf.Model:
    """The package as lib3mf reads it, strictly (a warning would be an error)."""
    model = lib3mf.get_wrapper().CreateModel()
    reader = model.QueryReader("3mf")
    reader.SetStrictModeActive(True)
    reader.ReadFromBuffer(bytearray(data))
    assert reader.GetWarningCount() == 0
    return model


def objects(model: lib3mf.Model) -> list[lib3mf.MeshObject]:
    found, iterator = [], model.GetMeshObjects()
    while iterator.MoveNext():
        found.append(iterator.GetCurrentMeshObject())
    return found


def arrays(mesh_object: lib3mf.MeshObject) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float vertices in mm and (F, 3) int triangles as lib3mf read them."""
    vertices = np.array([v.Coordinates[0:3] for v in mesh_object.GetVertices()], np.float64)
    faces = np.array([t.Indices[0:3] for t in mesh_object.GetTriangleIndices()], np.int64)
    return vertices, faces


def colour(model: lib3mf.Model, mesh_object: lib3mf.MeshObject) -> tuple[int, int, int, int]:
    """The object's base-material colour as 8-bit (r, g, b, alpha)."""
    resource, property_id, has_property = mesh_object.GetObjectLevelProperty()
    assert has_property
    group = model.GetBaseMaterialGroupByID(resource)
    rgba = group.GetDisplayColor(property_id)
    return rgba.Red, rgba.Green, rgba.Blue, rgba.Alpha


def metadata(model: lib3mf.Model) -> dict[str, str]:
    group = model.GetMetaDataGroup()
    entries = [group.GetMetaData(i) for i in range(group.GetMetaDataCount())]
    return {entry.GetName(): entry.GetValue() for entry in entries}


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """mm³; positive when the triangles wind counter-clockwise seen from outside."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def test_the_registry_has_3mf_as_one_binary_file() -> None:
    assert WRITERS["3mf"].mime == "model/3mf" and WRITERS["3mf"].binary
    assert not WRITERS["3mf"].one_mesh  # the package itself holds every part


def test_a_sphere_reads_back_in_lib3mf_in_millimetres(sphere: Mesh) -> None:
    data = export(sphere, "3mf", title="Sphere r80", metadata=METADATA)
    model = read_lib3mf(data)
    assert model.GetUnit() == lib3mf.ModelUnit.MilliMeter
    (only,) = objects(model)
    assert only.GetName() == "Sphere r80" and only.IsManifoldAndOriented()
    vertices, faces = arrays(only)
    np.testing.assert_array_equal(faces, sphere.faces)
    np.testing.assert_allclose(vertices, sphere.vertices, rtol=0, atol=COORD_TOL)
    # Outward winding: the enclosed volume is positive and that of the sphere (polyhedron).
    expected = signed_volume(sphere.vertices.astype(np.float64), sphere.faces)
    assert signed_volume(vertices, faces) == pytest.approx(expected, rel=1e-5)
    assert expected > 0.95 * 4 / 3 * np.pi * 80.0**3
    assert colour(model, only) == (*(round(255 * c) for c in BONE_RGB), 255)
    assert model.GetBuildItems().Count() == 1
    found = metadata(model)
    assert found["Title"] == "Sphere r80"
    assert found["software"] == "MISS 0.1.0" and found["level__HU_"] == "95.5"
    assert found["note"] == METADATA["note"]


def test_every_part_keeps_its_name_colour_opacity_and_triangles(scene: Scene) -> None:
    model = read_lib3mf(export(scene, "3mf"))
    found = objects(model)
    assert [o.GetName() for o in found] == [p.name for p in scene.parts]
    assert [colour(model, o) for o in found] == [
        (230, 178, 153, 102),  # opacity 0.4 as alpha
        (255, 255, 0, 255),
        (0, 51, 255, 255),
    ]
    for part, mesh_object in zip(scene.parts, found, strict=True):
        vertices, faces = arrays(mesh_object)
        np.testing.assert_array_equal(faces, part.mesh.faces)
        np.testing.assert_allclose(vertices, part.mesh.vertices, rtol=0, atol=COORD_TOL)
        closed = trimesh.Trimesh(part.mesh.vertices, part.mesh.faces, process=False).is_watertight
        assert mesh_object.IsManifoldAndOriented() == closed
    assert model.GetBuildItems().Count() == len(scene.parts)
    assert metadata(model)["Title"] == "Head"


def test_trimesh_reads_the_same_parts_closed_and_outward(scene: Scene) -> None:
    loaded = trimesh.load(io.BytesIO(export(scene, "3mf")), file_type="3mf", process=False)
    assert set(loaded.geometry) == {p.name for p in scene.parts}
    for part in scene.parts:
        mesh = loaded.geometry[part.name]
        assert len(mesh.faces) == part.mesh.n_triangles
        np.testing.assert_allclose(
            mesh.vertices[mesh.faces], part.mesh.vertices[part.mesh.faces], atol=COORD_TOL
        )
    skin, bone = loaded.geometry["skin & <scalp>"], loaded.geometry["bone"]
    assert skin.is_watertight and skin.is_winding_consistent and skin.volume > 0
    assert bone.is_watertight and bone.volume == pytest.approx(6000.0, rel=1e-4)


def test_a_triangle_with_a_repeated_vertex_is_left_out() -> None:
    """3MF forbids it (lib3mf refuses the whole file); it encloses nothing."""
    tetra = trimesh.creation.icosphere(subdivisions=0, radius=10.0)
    faces = np.vstack([tetra.faces, [[3, 3, 4]], [[5, 6, 5]]])
    mesh = Mesh(tetra.vertices.astype(np.float32), faces.astype(np.int32))
    (only,) = objects(read_lib3mf(export(mesh, "3mf")))
    np.testing.assert_array_equal(arrays(only)[1], tetra.faces)
    assert only.IsManifoldAndOriented()


def test_the_package_is_the_three_opc_parts_and_reproducible(scene: Scene) -> None:
    data = export(scene, "3mf", metadata=METADATA)
    assert data == export(scene, "3mf", metadata=METADATA)
    archive = zipfile.ZipFile(io.BytesIO(data))
    assert archive.namelist() == ["[Content_Types].xml", "_rels/.rels", MODEL_PATH]
    assert {info.date_time for info in archive.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    assert b'unit="millimeter"' in archive.read(MODEL_PATH)[:200]


def test_miss_convert_writes_a_3mf_by_its_extension(demo_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "bone.3mf"
    args = ["convert", str(demo_file), "--level", "300", "--sample-rate", "3", "--json"]
    proc = subprocess.run(
        [sys.executable, "-m", "miss.cli", *args, "-o", str(out)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    stats = json.loads(proc.stdout)
    model = read_lib3mf(out.read_bytes())
    found = objects(model)
    assert sum(o.GetTriangleCount() for o in found) == stats["triangles"]
    assert model.GetUnit() == lib3mf.ModelUnit.MilliMeter
