"""Structures: components, label maps with shared boundaries, multi-level scenes, scene export.

Analytic answers where they exist (ball volumes), real label maps otherwise (the
frog, TotalSegmentator over its CT), and independent readers for the files
(VTK's VRML importer, trimesh for glTF/OBJ/PLY/STL, lxml for X3D).
"""

from __future__ import annotations

import io
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
import vtk
from lxml import etree
from vtk.util import numpy_support

import miss
from miss._vtk import to_polydata
from miss.demo import phantom
from miss.errors import BadParameter, EmptySurface
from miss.export import WRITERS
from miss.geometry import boundary_edge_count, face_normals
from miss.measure._jit import distances_to
from miss.pipeline import run
from miss.scene import Part, Scene, linear_rgb
from miss.spec import JobSpec
from miss.structures.labelmap import align_labels, label_counts
from miss.structures.labels import find_label_table, parse_color_table, totalsegmentator_table
from miss.structures.labels_totalseg import TOTALSEG_TOTAL
from miss.types import Mesh, Volume

SPACING = (0.8, 0.8, 1.2)  # anisotropic on purpose: volumes must come out in mm³
BALLS = (((20.0, 20.0, 20.0), 12.0), ((52.0, 22.0, 24.0), 8.0), ((30.0, 50.0, 40.0), 5.0))

# The VTK frog's tissue names, written beside a copy of the map as a 3D Slicer table.
FROG_NAMES = {
    1: "blood", 2: "brain", 3: "duodenum", 4: "eye_retina", 5: "eye_white", 6: "heart",
    7: "ileum", 8: "kidney", 9: "l_intestine", 10: "liver", 11: "lung", 12: "nerve",
    13: "skeleton", 14: "spleen", 15: "stomach",
}  # fmt: skip


def _balls(balls=BALLS, size=(90, 80, 50)) -> Volume:
    """Signed distance (mm, positive inside) to separate balls: exact spheres at level 0."""
    affine = np.diag([*SPACING, 1.0])
    ijk = np.indices(size, dtype=np.float32)
    xyz = [ijk[a] * SPACING[a] for a in range(3)]
    field = np.full(size, -100.0, dtype=np.float32)
    for centre, radius in balls:
        d = np.sqrt(sum((xyz[a] - centre[a]) ** 2 for a in range(3)))
        field = np.maximum(field, radius - d)
    return Volume(np.asfortranarray(field), affine, {"units": ""})


def _sphere_ml(radius: float) -> float:
    return 4.0 / 3.0 * math.pi * radius**3 / 1000.0


# ---------------------------------------------------------------- components


def test_split_gives_one_part_per_ball_with_its_volume_largest_first() -> None:
    scene = miss.extract_scene(
        _balls(), levels=0.0, components="split", decimate="none", measure=False
    )
    assert len(scene.parts) == 3
    expected = sorted((_sphere_ml(r) for _, r in BALLS), reverse=True)
    for part, ml in zip(scene.parts, expected, strict=True):
        assert part.volume_ml == pytest.approx(ml, rel=0.03)
        assert boundary_edge_count(part.mesh.faces) == 0
    assert [p.name for p in scene.parts] == ["level 0 1", "level 0 2", "level 0 3"]
    assert len({p.color for p in scene.parts}) == 3  # pieces told apart by colour


def test_largest_keeps_only_the_biggest_ball() -> None:
    scene = miss.extract_scene(_balls(), levels=0.0, components="largest", decimate="none")
    assert len(scene.parts) == 1
    assert scene.parts[0].volume_ml == pytest.approx(_sphere_ml(12.0), rel=0.03)
    centre = scene.parts[0].mesh.vertices.mean(axis=0)
    assert np.allclose(centre, BALLS[0][0], atol=0.5)


def test_min_size_leaves_small_pieces_out_with_a_note() -> None:
    # The 5 mm ball holds 0.52 mL = 524 mm³; 1000 mm³ drops it and keeps the others.
    scene = miss.extract_scene(
        _balls(), levels=0.0, components="split", min_size_mm3=1000, decimate="none"
    )
    assert len(scene.parts) == 2
    assert any("1 smaller piece" in note for note in scene.notes)
    with pytest.raises(EmptySurface, match="lower the minimum size"):
        miss.extract_scene(_balls(), levels=0.0, components="split", min_size_mm3=1e7)


def test_a_hollow_ball_is_one_piece_not_two_shells() -> None:
    shell = _balls(balls=(((28.0, 28.0, 30.0), 14.0),))
    hollow = np.minimum(shell.data, -(shell.data - 6.0))  # inside for 8 mm < r < 14 mm
    scene = miss.extract_scene(
        Volume(np.asfortranarray(hollow), shell.affine, {}), levels=0.0, components="split",
        decimate="none",
    )  # fmt: skip
    assert len(scene.parts) == 1
    assert scene.parts[0].volume_ml == pytest.approx(_sphere_ml(14) - _sphere_ml(8), rel=0.03)


def test_bad_structure_options_say_what_to_do() -> None:
    with pytest.raises(BadParameter, match="all, largest, split"):
        miss.extract_scene(_balls(), levels=0.0, components="biggest")
    with pytest.raises(BadParameter, match="labels"):
        miss.extract_scene(_balls(), labels="liver")
    with pytest.raises(BadParameter, match="give a threshold"):
        miss.extract_scene(_balls())
    with pytest.raises(BadParameter, match="passband"):
        miss.extract_scene(_balls(), levels=0.0, smooth=10, passband=3.0)


# ---------------------------------------------------------------- smoothing and levels


def test_smoothing_keeps_the_volume_within_2_percent() -> None:
    raw = miss.extract_scene(_balls(), levels=0.0, decimate="none").parts[0]
    smooth = miss.extract_scene(_balls(), levels=0.0, smooth=30, decimate="none").parts[0]
    assert smooth.volume_ml == pytest.approx(raw.volume_ml, rel=0.02)
    assert not np.allclose(smooth.mesh.vertices, raw.mesh.vertices)  # it did smooth


def test_how_far_smoothing_moved_each_part_is_reported() -> None:
    """Issue 42: smoothing's effect, measured against the unsmoothed surface and reported
    beside the bound: each smoothed part's largest and mean vertex displacement (mm), exactly
    the distance between the same vertices before and after; none for an unsmoothed part."""
    raw = miss.extract_scene(_balls(), levels=0.0, decimate="none").parts[0]
    smooth = miss.extract_scene(_balls(), levels=0.0, smooth=20, decimate="none").parts[0]
    moved = np.linalg.norm(
        smooth.mesh.vertices.astype(np.float64) - raw.mesh.vertices.astype(np.float64), axis=1
    )
    assert raw.smoothed_mm is None and "smoothing_max_mm" not in raw.summary()
    assert smooth.smoothed_mm == pytest.approx((moved.max(), moved.mean()), rel=1e-4)
    assert 0 < smooth.summary()["smoothing_mean_mm"] < smooth.summary()["smoothing_max_mm"]
    decimated = miss.extract_scene(_balls(), levels=0.0, smooth=20).parts[0]
    assert decimated.smoothed_mm == pytest.approx(smooth.smoothed_mm)  # before decimation


def test_smoothing_a_voxel_ball_label_recovers_the_sphere() -> None:
    # Surface nets of a label ball are voxel blocks; windowed sinc rounds them off
    # without shrinking: the volume stays within 2 % of the voxels' and of the sphere's.
    field = _balls(balls=(((28.0, 28.0, 30.0), 12.0),))
    labels = Volume(np.asfortranarray((field.data > 0).astype(np.uint8) * 3), field.affine, {})
    voxels_ml = label_counts(labels)[3] * np.prod(SPACING) / 1000
    part = miss.extract_scene(labels, labels="all", decimate="none").parts[0]
    assert part.label == 3
    assert part.volume_ml == pytest.approx(voxels_ml, rel=0.02)
    assert part.volume_ml == pytest.approx(_sphere_ml(12.0), rel=0.02)


def test_two_levels_on_the_phantom_give_translucent_skin_over_opaque_bone() -> None:
    scene = miss.extract_scene(phantom(), levels=[300, -500], measure=False)
    assert [p.name for p in scene.parts] == ["bone (300 HU)", "skin (-500 HU)"]
    bone, skin = scene.parts
    assert skin.opacity < 1.0 and bone.opacity == 1.0
    assert skin.volume_ml > bone.volume_ml > 0  # the head holds the skull
    assert skin.color != bone.color


# ---------------------------------------------------------------- label tables


def test_slicer_and_itksnap_colour_tables_parse() -> None:
    slicer = parse_color_table("# Slicer\n0 Background 0 0 0 0\n5 left liver 221 130 101 255\n")
    assert slicer[5].name == "left liver"
    assert slicer[5].color == pytest.approx((221 / 255, 130 / 255, 101 / 255))
    assert slicer[0].opacity == 1.0  # a listed structure is never invisible
    snap = parse_color_table('################\n    7   255  0  0   0.5  1  1    "Bone # 2"\n')
    assert snap[7].name == "Bone # 2" and snap[7].opacity == 0.5
    with pytest.raises(miss.UnreadableVolume, match="line 1"):
        parse_color_table("liver 1 2 3\n")


def test_totalsegmentator_table_lists_117_structures() -> None:
    assert sorted(TOTALSEG_TOTAL) == list(range(1, 118))
    assert TOTALSEG_TOTAL[5] == "liver" and TOTALSEG_TOTAL[52] == "aorta"
    assert totalsegmentator_table()[27].name == "vertebrae_L5"


# ---------------------------------------------------------------- the frog label map


@pytest.fixture(scope="module")
def frog_copy(datasets: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The frog map copied beside a 3D Slicer colour table naming labels 1-15."""
    folder = tmp_path_factory.mktemp("frog")
    for name in ("frogtissue.mhd", "frogtissue.zraw"):
        shutil.copy(datasets / "labels_frogtissue" / name, folder / name)
    rows = [f"{k} {v} {40 + 10 * k} {200 - 10 * k} {90 + 5 * k} 255" for k, v in FROG_NAMES.items()]
    (folder / "frogtissue.ctbl").write_text("# index name r g b a\n" + "\n".join(rows) + "\n")
    return folder / "frogtissue.mhd"


@pytest.fixture(scope="module")
def frog(frog_copy: Path) -> tuple[Volume, Scene]:
    volume = miss.load_volume(frog_copy)
    return volume, miss.extract_scene(
        volume, labels="all", table=str(frog_copy.with_suffix(".ctbl")), measure=False
    )


@pytest.mark.slow
def test_frog_gives_one_closed_surface_per_label_present(frog: tuple[Volume, Scene]) -> None:
    volume, scene = frog
    present = label_counts(volume)
    assert len(present) == 25
    assert [p.label for p in scene.parts] == sorted(present)
    voxel_ml = np.prod(volume.spacing) / 1000
    for part in scene.parts:
        assert boundary_edge_count(part.mesh.faces) == 0, part.name
        assert part.volume_ml > 0, part.name  # faces wound outward
        if present[part.label] > 100_000:  # thin and small ones lose volume (noted)
            assert part.volume_ml == pytest.approx(present[part.label] * voxel_ml, rel=0.05)
    assert scene.parts[9].name == "liver" and scene.parts[20].name == "label 24"


def _adjacent_pairs(data: np.ndarray, count: int) -> list[tuple[int, int]]:
    """The label pairs that touch across the most voxel faces (background left out)."""
    touching: dict[tuple[int, int], int] = {}
    for axis in range(3):
        a = np.moveaxis(data, axis, 0)[:-1].ravel()
        b = np.moveaxis(data, axis, 0)[1:].ravel()
        keep = (a != b) & (a > 0) & (b > 0)
        pairs, n = np.unique(
            np.sort(np.stack([a[keep], b[keep]], 1), 1), axis=0, return_counts=True
        )
        for pair, k in zip(map(tuple, pairs), n, strict=True):
            touching[pair] = touching.get(pair, 0) + int(k)
    return sorted(touching, key=touching.get, reverse=True)[:count]


def _inside(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    """Which points lie inside the closed ``mesh`` (VTK ray casting: independent of MISS)."""
    cloud = vtk.vtkPolyData()
    cloud.SetPoints(vtk.vtkPoints())
    cloud.GetPoints().SetData(
        numpy_support.numpy_to_vtk(np.ascontiguousarray(points, float), deep=True)
    )
    select = vtk.vtkSelectEnclosedPoints()
    select.SetInputData(cloud)
    select.SetSurfaceData(to_polydata(mesh.vertices, mesh.faces))
    select.SetTolerance(1e-6)
    select.Update()
    mask = select.GetOutput().GetPointData().GetArray("SelectedPoints")
    return numpy_support.vtk_to_numpy(mask).astype(bool)


def _voxel_index(volume: Volume, points: np.ndarray) -> np.ndarray:
    ijk = (points - volume.affine[:3, 3]) @ np.linalg.inv(volume.affine[:3, :3]).T
    return np.clip(np.rint(ijk).astype(int), 1, np.array(volume.dims) - 2)


def _only_between(volume: Volume, points: np.ndarray, a: int, b: int) -> np.ndarray:
    """Points whose 3x3x3 voxel neighbourhood holds labels a and b and nothing else."""
    idx = _voxel_index(volume, points)
    ok = np.ones(len(points), dtype=bool)
    seen_a, seen_b = np.zeros_like(ok), np.zeros_like(ok)
    for offset in np.ndindex(3, 3, 3):
        i, j, k = (idx + np.array(offset) - 1).T
        value = volume.data[i, j, k]
        ok &= (value == a) | (value == b)
        seen_a |= value == a
        seen_b |= value == b
    return ok & seen_a & seen_b


def test_frog_neighbours_share_their_boundary_after_decimation(
    frog: tuple[Volume, Scene],
) -> None:
    volume, scene = frog
    parts = {p.label: p for p in scene.parts}
    rng = np.random.default_rng(1)
    for a, b in _adjacent_pairs(volume.data, 3):
        centres, _ = _face_samples(parts[a].mesh)
        # On the a|b interface by the voxels' word, away from where a third label joins.
        on = np.flatnonzero(_only_between(volume, centres, a, b))
        pick = rng.choice(on, size=min(400, len(on)), replace=False)
        assert len(pick) >= 30, (a, b)
        assert distances_to(centres[pick], parts[b].mesh).max() < 1e-3  # the very same surface


@pytest.mark.slow
def test_frog_parts_leave_no_gap_and_no_overlap_where_organs_meet(frog_copy: Path) -> None:
    # Undecimated: independent patch decimation may cross within its error bound near
    # the curves where three labels meet; the extraction itself must be exact. One
    # closed surface per label from its own threshold leaves gaps here (4-5 % of points).
    volume = miss.load_volume(frog_copy)
    scene = miss.extract_scene(volume, labels="all", decimate="none", measure=False)
    parts = {p.label: p for p in scene.parts}
    rng = np.random.default_rng(2)
    for a in (6, 10, 11):  # heart, liver, lung: their neighbours, junctions included
        centres, normals = _face_samples(parts[a].mesh)
        inner = np.flatnonzero(_no_background(volume, centres))
        pick = rng.choice(inner, size=min(600, len(inner)), replace=False)
        assert len(pick) >= 300, a
        outward = centres[pick] + 0.05 * normals[pick]
        inward = centres[pick] - 0.05 * normals[pick]
        hits_out = sum(_inside(p.mesh, outward).astype(int) for p in scene.parts)
        hits_in = sum(_inside(p.mesh, inward).astype(int) for p in scene.parts)
        assert not _inside(parts[a].mesh, outward).any(), a
        assert (hits_out == 1).all(), a  # just outside a: inside exactly one neighbour (no gap)
        assert (hits_in == 1).all() and _inside(parts[a].mesh, inward).all(), a  # no overlap


def _face_samples(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Triangle centres (F, 3) and unit outward normals (F, 3), mm."""
    normals = face_normals(mesh.vertices, mesh.faces)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    return mesh.vertices[mesh.faces].mean(axis=1).astype(np.float64), normals


def _no_background(volume: Volume, points: np.ndarray) -> np.ndarray:
    """Points with no background voxel (0) within two voxels: smoothing rounds corners
    off by about one, so a point nearer the background may be on a background face."""
    idx = np.clip(_voxel_index(volume, points), 2, np.array(volume.dims) - 3)
    ok = np.ones(len(points), dtype=bool)
    for offset in np.ndindex(5, 5, 5):
        i, j, k = (idx + np.array(offset) - 2).T
        ok &= volume.data[i, j, k] != 0
    return ok


def test_frog_colour_table_beside_the_map_is_found(frog_copy: Path) -> None:
    table, source = find_label_table(frog_copy)
    assert source == "frogtissue.ctbl"
    assert table[13].name == "skeleton"
    assert table[13].color == pytest.approx((170 / 255, 70 / 255, 155 / 255))


def test_frog_names_and_colours_reach_vrml(frog: tuple[Volume, Scene], tmp_path: Path) -> None:
    _, scene = frog
    chosen = Scene(tuple(p for p in scene.parts if p.label in (2, 10, 13)), "frog organs")
    text = miss.export(chosen, "wrl").decode()
    assert text.count(" Shape {") == 3 and 'title "frog organs"' in text
    path = tmp_path / "frog.wrl"
    path.write_text(text)
    vtk.vtkObject.GlobalWarningDisplayOff()
    importer = vtk.vtkVRMLImporter()
    importer.SetFileName(str(path))
    window = vtk.vtkRenderWindow()
    window.SetOffScreenRendering(1)
    importer.SetRenderWindow(window)
    importer.Update()
    for part in chosen.parts:
        actor = importer.GetVRMLDEFObject(part.name)  # the names are already safe words
        assert actor is not None, part.name
        assert actor.GetProperty().GetDiffuseColor() == pytest.approx(part.color, abs=1e-4)
        assert actor.GetProperty().GetOpacity() == pytest.approx(1.0)
        cells = actor.GetMapper().GetInput().GetNumberOfCells()
        assert cells >= part.mesh.n_triangles


def test_frog_names_and_colours_reach_gltf(frog: tuple[Volume, Scene]) -> None:
    _, scene = frog
    skin_like = Part("outer skin", scene.parts[0].mesh, (0.8, 0.6, 0.5), 0.4, None)
    chosen = Scene((*(p for p in scene.parts if p.label in (2, 10, 13)), skin_like), "frog")
    loaded = trimesh.load(io.BytesIO(miss.export(chosen, "glb")), file_type="glb")
    assert set(loaded.geometry) == {p.name for p in chosen.parts}
    assert set(loaded.graph.nodes_geometry) == {p.name for p in chosen.parts}
    for part in chosen.parts:
        geometry = loaded.geometry[part.name]
        assert len(geometry.faces) == part.mesh.n_triangles
        factor = np.asarray(geometry.visual.material.baseColorFactor, float) / 255
        assert factor[:3] == pytest.approx(linear_rgb(part.color), abs=0.01)
        assert factor[3] == pytest.approx(part.opacity, abs=0.01)
    assert loaded.geometry["outer skin"].visual.material.alphaMode == "BLEND"
    # The compressed file carries the same names and materials in its JSON chunk.
    packed = miss.export(chosen, "glb", compress=True)
    document = json.loads(packed[20 : 20 + int.from_bytes(packed[12:16], "little")])
    assert [m["name"] for m in document["meshes"]] == [p.name for p in chosen.parts]
    assert document["materials"][-1]["alphaMode"] == "BLEND"


# ---------------------------------------------------------------- a label map over its CT


def _centroid_mm(volume: Volume, label: int) -> np.ndarray:
    ijk = np.argwhere(volume.data == label).astype(np.float64)
    return (ijk @ volume.affine[:3, :3].T + volume.affine[:3, 3]).mean(axis=0)


def _solid_centroid(mesh: Mesh) -> np.ndarray:
    """Centre of mass of the solid a closed mesh bounds (signed tetrahedra to the origin)."""
    a, b, c = (mesh.vertices[mesh.faces[:, i]].astype(np.float64) for i in range(3))
    volumes = np.einsum("ij,ij->i", a, np.cross(b, c))
    return (volumes[:, None] * (a + b + c)).sum(axis=0) / (4 * volumes.sum())


def test_totalseg_map_of_30_slices_aligns_over_its_112_slice_ct(datasets: Path) -> None:
    folder = datasets / "ct_abdomen_totalseg"
    ct = miss.load_volume(folder / "example_ct.nii.gz")
    seg = miss.load_volume(folder / "example_seg.nii.gz")
    assert seg.dims[2] == 30 and ct.dims[2] == 112
    aligned = align_labels(seg, ct)
    assert aligned.dims == ct.dims
    for label in (5, 52, 31):  # liver, aorta, vertebra L1
        assert np.allclose(_centroid_mm(aligned, label), _centroid_mm(seg, label), atol=1e-6)
    scene = miss.extract_scene(
        ct, label_map=seg, labels=[5, 52], table=str(folder / "example_seg.nii.gz"), measure=False
    )
    assert [p.name for p in scene.parts] == ["liver", "aorta"]
    liver = scene.parts[0]
    assert np.allclose(_solid_centroid(liver.mesh), _centroid_mm(seg, 5), atol=1.0)
    assert liver.volume_ml == pytest.approx(label_counts(seg)[5] * 27 / 1000, rel=0.05)


def test_totalseg_map_aligns_over_its_dicom_ct_through_a_flip(datasets: Path) -> None:
    # The NIfTI map runs its rows the other way from the DICOM series: the liver's
    # voxels must land on liver-density CT (contrast-enhanced, about 60-150 HU).
    folder = datasets / "ct_abdomen_totalseg"
    ct = miss.load_volume(folder / "dicom")
    seg = miss.load_volume(folder / "example_seg_dicom.nii.gz")
    assert np.sign(ct.affine[1, 1]) != np.sign(seg.affine[1, 1])
    aligned = align_labels(seg, ct)
    assert np.allclose(_centroid_mm(aligned, 5), _centroid_mm(seg, 5), atol=1e-6)
    assert 40 < float(np.asarray(ct.data)[aligned.data == 5].mean()) < 200


def test_a_label_map_elsewhere_in_space_is_refused() -> None:
    far = np.diag([1.0, 1.0, 1.0, 1.0])
    far[0, 3] = 1e4  # 10 m to the left of the volume
    labels = Volume(np.ones((4, 4, 4), np.uint8, order="F"), far, {})
    with pytest.raises(BadParameter, match="does not overlap"):
        align_labels(labels, _balls())


# ---------------------------------------------------------------- scene export


@pytest.fixture(scope="module")
def head() -> Scene:
    return miss.extract_scene(phantom(64, 3.0), levels=[-500, 300], measure=False, title="head")


def test_x3d_scene_has_a_named_shape_per_part(head: Scene) -> None:
    root = etree.fromstring(miss.export(head, "x3d"))
    shapes = root.findall(".//Shape")
    assert [s.get("DEF") for s in shapes] == ["skin_500_HU", "bone_300_HU"]
    assert shapes[0].find("MetadataString").get("value") == '"skin (-500 HU)"'
    transparency = [float(s.find(".//Material").get("transparency")) for s in shapes]
    assert transparency == pytest.approx([0.65, 0.0])


@pytest.mark.parametrize("fmt", ["stl", "ply", "obj"])
def test_a_scene_in_a_one_mesh_format_is_one_file_of_that_format(head: Scene, fmt: str) -> None:
    """Not a zip (trimesh took those for empty scenes): one file with every part's
    triangles, served under the format's own type; OBJ keeps a named group per part."""
    data = miss.export(head, fmt)
    assert data[:2] != b"PK" and WRITERS[fmt].mime == f"model/{fmt}"
    loaded = trimesh.load(io.BytesIO(data), file_type=fmt, process=False, split_objects=True)
    meshes = loaded.geometry if isinstance(loaded, trimesh.Scene) else {"": loaded}
    assert sum(len(m.faces) for m in meshes.values()) == head.n_triangles
    if fmt == "obj":
        counts = {name: len(m.faces) for name, m in meshes.items()}
        names = ["skin_500_HU", "bone_300_HU"]
        assert counts == {k: p.mesh.n_triangles for k, p in zip(names, head.parts, strict=True)}
    assert data == miss.export(head, fmt)  # reproducible bytes


def test_a_ply_scene_colours_each_part_s_faces_and_names_them(head: Scene) -> None:
    data = miss.export(head, "ply")
    loaded = trimesh.load(io.BytesIO(data), file_type="ply", process=False)
    first = head.parts[0].mesh.n_triangles
    rgba = [[round(255 * c) for c in (*p.color, p.opacity)] for p in head.parts]
    colours = loaded.visual.face_colors
    assert (colours[:first] == rgba[0]).all() and (colours[first:] == rgba[1]).all()
    header = data[: data.index(b"end_header")].decode("ascii")
    assert f"comment part 1: skin (-500 HU), faces 0..{first - 1}" in header
    assert f"comment part 2: bone (300 HU), faces {first}..{head.n_triangles - 1}" in header


def test_a_plain_mesh_exports_exactly_as_before(head: Scene) -> None:
    mesh = head.parts[1].mesh
    assert miss.export(mesh, "wrl").startswith(b"#VRML V2.0 utf8")
    assert b"DEF " not in miss.export(mesh, "wrl")
    assert trimesh.load(io.BytesIO(miss.export(mesh, "glb")), file_type="glb").geometry.keys() == {
        "surface"
    }


# ---------------------------------------------------------------- pipeline


def test_old_job_specs_keep_their_cache_key() -> None:
    import hashlib

    old = {"level": 300.0, "sample_rate": [1, 1, 1], "start_slice": None, "end_slice": None,
           "roi": None, "decimate": "quadric", "error_bound": 0.0002, "reduce": 0.9,
           "max_error": 0.01}  # fmt: skip
    expected = hashlib.sha256(json.dumps(old, sort_keys=True).encode()).hexdigest()[:32]
    # models made before bounds were held used the paper's schedule and the bound 0.0002:
    # those find them; the default now holds a bound of 0.002, another model, another key
    old_default = {"schedule": "paper", "error_bound": 0.0002}
    assert JobSpec.of(level=300.0, **old_default).key() == expected
    assert JobSpec.of(level=300.0).key() != expected
    assert JobSpec.of(level=300.0, schedule="paper").key() != expected
    assert JobSpec.of(level=300.0, levels=(300.0, -500.0), **old_default).key() != expected


def test_run_builds_a_scene_from_levels() -> None:
    spec = JobSpec.from_dict({"levels": [-500, 300], "formats": ["glb", "wrl"]})
    result = run(phantom(64, 3.0), spec)
    assert result.scene is not None and len(result.scene.parts) == 2
    stats = result.stats()
    assert [p["name"] for p in stats["parts"]] == ["skin (-500 HU)", "bone (300 HU)"]
    assert stats["triangles"] == result.scene.n_triangles
    assert result.artifacts["wrl"].count(b" Shape {") == 2


def test_a_scenes_report_names_the_methods_that_made_its_parts() -> None:
    from miss.decimate import DecimationReport
    from miss.structures.build import combined_report

    def part(finished_with: str | None, method: str = "quadric") -> DecimationReport:
        return DecimationReport(
            method=method, reduce=0.9, error_bound=0.002, triangles_in=100, triangles_out=20,
            achieved_reduction=0.8, final_bound_mm=1.0, max_error_mm=0.5, mean_error_mm=0.1,
            seconds=0.1, measure_seconds=0.0, finished_with=finished_with,
        )  # fmt: skip

    assert combined_report([part("schroeder"), part("schroeder")]).finished_with == "schroeder"
    # a part kept whole was not decimated: the others' method made the scene
    assert combined_report([part("schroeder"), part("none")]).finished_with == "schroeder"
    mixed = combined_report([part("schroeder"), part("quadric"), part(None)])
    assert mixed.finished_with == "quadric/schroeder"
    assert combined_report([part("none", "none")]).summary()["finished_with"] == "none"


@pytest.mark.parametrize("schedule", ["paper", "guaranteed"])
def test_a_label_map_job_keeps_its_schedule(schedule: str) -> None:
    """A label map decimated by vertex removal runs the schedule the job asked for (it
    used to run "guaranteed" whatever was asked)."""
    field = _balls(balls=(((28.0, 28.0, 30.0), 12.0),))
    labels = Volume(np.asfortranarray((field.data > 0).astype(np.uint8) * 3), field.affine, {})
    spec = JobSpec.of(
        labels="all", decimate="schroeder", schedule=schedule, reduce=0.9, formats=("glb",)
    )
    assert run(labels, spec).report.schedule == schedule
