"""The command line's structure options, run as a user runs them (real processes)."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import pytest
import trimesh

# the same subprocess runner as the core CLI tests
from test_cli import miss


def test_two_levels_give_translucent_skin_and_opaque_bone(demo_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "head.wrl"
    args = ["convert", str(demo_file), "--level", "-500", "--level", "300", "-o", str(out)]
    stats = json.loads(miss(*args, "--json").stdout)
    assert [p["name"] for p in stats["parts"]] == ["skin (-500 HU)", "bone (300 HU)"]
    assert [p["opacity"] for p in stats["parts"]] == [0.35, 1.0]
    assert set(stats["parts"][0]) >= {
        "name",
        "label",
        "color",
        "triangles",
        "volume_ml",
        "area_cm2",
    }
    assert stats["triangles"] == sum(p["triangles"] for p in stats["parts"])
    assert out.read_text().count(" Shape {") == 2


def test_two_levels_in_files_other_tools_open(demo_file: Path, tmp_path: Path) -> None:
    """STL, PLY, OBJ and the plain GLB of two parts: each one file of its format with both
    parts' triangles (the first three were zips); OBJ and GLB name the parts; the plain
    GLB needs no glTF extension."""
    names = ["head.stl", "head.ply", "head.obj", "head.plain.glb"]
    outs = [str(tmp_path / name) for name in names]
    args = ["convert", str(demo_file), "--level", "-500", "--level", "300", "--json"]
    stats = json.loads(miss(*args, *(x for out in outs for x in ("-o", out))).stdout)
    assert sorted(Path(o["path"]).name for o in stats["outputs"]) == sorted(names)
    parts = {p["name"]: p["triangles"] for p in stats["parts"]}
    for name in names:
        kind = name.rsplit(".", 1)[1]
        loaded = trimesh.load(tmp_path / name, file_type=kind, process=False, split_objects=True)
        meshes = loaded.geometry if isinstance(loaded, trimesh.Scene) else {"": loaded}
        assert sum(len(m.faces) for m in meshes.values()) == stats["triangles"], name
    obj = trimesh.load(tmp_path / "head.obj", file_type="obj", split_objects=True)
    assert {k: len(m.faces) for k, m in obj.geometry.items()} == {
        "skin_500_HU": parts["skin (-500 HU)"], "bone_300_HU": parts["bone (300 HU)"]
    }  # fmt: skip
    glb = trimesh.load(tmp_path / "head.plain.glb", file_type="glb", process=False)
    assert {k: len(m.faces) for k, m in glb.geometry.items()} == parts
    data = (tmp_path / "head.plain.glb").read_bytes()
    document = json.loads(data[20 : 20 + int.from_bytes(data[12:16], "little")])
    assert "extensionsRequired" not in document and "extensionsUsed" not in document


@pytest.mark.slow
def test_components_split_finds_the_lesion_apart_from_the_skull(
    demo_file: Path, tmp_path: Path
) -> None:
    # Halfway between brain (35 HU) and lesion (400 HU); the lesion is a ball only 4 voxels
    # across, whose corners marching cubes cuts: about 0.8 of its true volume.
    out = tmp_path / "bones.glb"
    args = ["convert", str(demo_file), "--level", "218", "--components", "split", "-o", str(out)]
    parts = json.loads(miss(*args, "--decimate", "none", "--json").stdout)["parts"]
    assert [p["name"] for p in parts] == ["bone (218 HU) 1", "bone (218 HU) 2"]
    lesion_ml = 4 / 3 * math.pi * 6**3 / 1000
    assert 0.7 * lesion_ml < parts[1]["volume_ml"] < lesion_ml
    assert parts[0]["volume_ml"] > 100 * parts[1]["volume_ml"]
    loaded = trimesh.load(out, file_type="glb")
    assert set(loaded.geometry) == {"bone (218 HU) 1", "bone (218 HU) 2"}
    largest = ["--components", "largest", "-o", str(tmp_path / "skull.stl"), "--json"]
    assert len(json.loads(miss(*args[:4], *largest).stdout)["parts"]) == 1
    small = ["--min-size", "2000", "--json"]
    assert len(json.loads(miss(*args, *small).stdout)["parts"]) == 1


@pytest.mark.slow
def test_labels_of_the_frog_with_a_colour_table(datasets: Path, tmp_path: Path) -> None:
    for name in ("frogtissue.mhd", "frogtissue.zraw"):
        shutil.copy(datasets / "labels_frogtissue" / name, tmp_path / name)
    (tmp_path / "tissues.txt").write_text("1 blood 200 30 30 255\n4 eye_retina 40 40 40 255\n")
    out = tmp_path / "frog.stl"
    args = ["convert", str(tmp_path / "frogtissue.mhd"), "--labels", "1,4,7", "-o", str(out)]
    stats = json.loads(miss(*args, "--label-table", str(tmp_path / "tissues.txt"), "--json").stdout)
    assert [(p["label"], p["name"]) for p in stats["parts"]] == [
        (1, "blood"), (4, "eye_retina"), (7, "label 7")
    ]  # fmt: skip
    assert stats["parts"][0]["color"] == pytest.approx([200 / 255, 30 / 255, 30 / 255], abs=1e-4)
    solid = trimesh.load(out, file_type="stl", process=False)  # one solid, no longer a zip
    assert len(solid.faces) == sum(p["triangles"] for p in stats["parts"])


def test_info_lists_the_labels_of_a_label_map_with_names(datasets: Path) -> None:
    path = datasets / "ct_abdomen_totalseg" / "example_seg.nii.gz"
    info = json.loads(miss("info", str(path), "--json").stdout)
    labels = {item["label"]: item for item in info["labels"]}
    assert len(labels) == 41
    assert labels[5]["name"] == "liver" and labels[5]["voxels"] == 38634
    assert labels[5]["volume_ml"] == pytest.approx(38634 * 27 / 1000)
    assert info["label_table"].startswith("NIfTI header label table")


def test_info_sums_up_an_8_bit_image_that_passes_for_a_label_map(datasets: Path) -> None:
    # a windowed CT stored as uint8: every value 1..255 would be a "label" line of its own
    path = datasets / "nifti" / "CT_pitch.nii.gz"
    lines = miss("info", str(path)).stdout.splitlines()
    assert len(lines) < 10
    (summary,) = [line for line in lines if line.startswith("label")]
    assert summary.startswith("labels    253 values besides 0 (1 .. 255), none named")
    assert len(json.loads(miss("info", str(path), "--json").stdout)["labels"]) == 253


def test_info_lists_each_label_of_a_small_label_map(datasets: Path) -> None:
    lines = miss("info", str(datasets / "labels_frogtissue" / "frogtissue.mhd")).stdout
    assert sum(line.startswith("label     ") for line in lines.splitlines()) == 25


def test_info_of_a_scan_lists_no_labels(demo_file: Path) -> None:
    assert "labels" not in json.loads(miss("info", str(demo_file), "--json").stdout)


def test_labels_of_a_scan_are_refused_on_one_line(demo_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "x.wrl"
    proc = miss("convert", str(demo_file), "--labels", "all", "-o", str(out), check=False)
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1 and "label map" in proc.stderr
    assert not out.exists()
