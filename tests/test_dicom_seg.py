"""DICOM SEG and RT-STRUCT as label maps: TotalSegmentator's labels through a real SEG,
analytic shapes through an RT-STRUCT, bad input, the confined reader, the scene."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import landlockpy
import numpy as np
import pydicom
import pytest
from pacs.dicom_data import (
    ABDOMEN,
    Roi,
    read_series,
    rtstruct_rois,
    write_ct_series,
    write_rtstruct,
    write_seg,
    write_small_seg,
)

import miss
from miss.errors import BadParameter, InputTooLarge, UnreadableSegmentation
from miss.io import confined, dicom_seg
from miss.io.dicom_seg import polygon_mask, read_rtstruct, read_seg, segmentation_kind
from miss.structures.labels import totalsegmentator_table
from miss.structures.labels_totalseg import TOTALSEG_TOTAL
from miss.types import Volume

needs_landlock = pytest.mark.skipif(
    landlockpy.abi_version() < 1,
    reason="this kernel has no Landlock (Linux 5.13+ with Landlock in its LSM list)",
)


@pytest.fixture(scope="module")
def abdomen_seg(datasets: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_seg(tmp_path_factory.mktemp("seg"), datasets)


@pytest.fixture(scope="module")
def phantom(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A synthetic 64 x 56 x 12 CT series (0.8 x 0.8 x 2.5 mm) and its RT-STRUCT."""
    folder = tmp_path_factory.mktemp("phantom")
    write_ct_series(folder / "ct")
    write_rtstruct(folder / "ct", folder / "rt")
    return folder


def _grid(series: Path) -> Volume:
    slices, affine = read_series(series)
    dims = (int(slices[0].Columns), int(slices[0].Rows), len(slices))
    return Volume(np.zeros(dims, np.uint8), affine)


# --------------------------------------------------------------------------- DICOM SEG


@pytest.mark.slow
def test_seg_of_totalsegmentator_labels_matches_the_nifti_voxel_for_voxel(
    abdomen_seg: Path, datasets: Path
) -> None:
    import nibabel as nib

    labels, table = read_seg(abdomen_seg)
    nifti = nib.load(datasets / ABDOMEN / "example_seg_dicom.nii.gz")
    truth = np.asarray(nifti.dataobj)
    # Both grids in LPS mm: the SEG's index -> the NIfTI's index is a flip of whole voxels.
    to_nifti = np.linalg.inv(np.diag([-1.0, -1, 1, 1]) @ nifti.affine) @ labels.affine
    assert np.allclose(to_nifti, np.round(to_nifti), atol=1e-3)
    i, j, k = np.indices(labels.dims).reshape(3, -1)
    n = np.round(to_nifti[:3, :3] @ np.stack([i, j, k]) + to_nifti[:3, 3:4]).astype(int)
    on_seg_grid = truth[n[0], n[1], n[2]].reshape(labels.dims)

    by_name = {name: number for number, name in TOTALSEG_TOTAL.items()}
    assert sorted(info.name for info in table.values()) == sorted(
        TOTALSEG_TOTAL[v] for v in np.unique(truth) if v
    )
    assert len(table) == 31
    expected = np.zeros(labels.dims, np.uint16)
    for number, info in table.items():
        expected[on_seg_grid == by_name[info.name]] = number
    assert np.array_equal(labels.data, expected)  # every voxel of every one of 31 labels

    colors = totalsegmentator_table()
    for info in table.values():  # CIELab 16-bit and back: within one step of 255
        assert np.allclose(info.color, colors[by_name[info.name]].color, atol=1.01 / 255)


def test_the_builders_reference_their_series(
    abdomen_seg: Path, datasets: Path, phantom: Path
) -> None:
    ct = read_series(datasets / ABDOMEN / "dicom")[0]
    seg = pydicom.dcmread(abdomen_seg, stop_before_pixels=True)
    assert seg.StudyInstanceUID == ct[0].StudyInstanceUID
    assert seg.FrameOfReferenceUID == ct[0].FrameOfReferenceUID
    (series,) = seg.ReferencedSeriesSequence
    assert series.SeriesInstanceUID == ct[0].SeriesInstanceUID
    assert len(series.ReferencedInstanceSequence) == len(ct) == 20
    images = read_series(phantom / "ct")[0]
    rt = pydicom.dcmread(phantom / "rt" / "rtstruct.dcm")
    assert rt.StudyInstanceUID == images[0].StudyInstanceUID
    (frame,) = rt.ReferencedFrameOfReferenceSequence
    assert frame.FrameOfReferenceUID == images[0].FrameOfReferenceUID
    referenced = frame.RTReferencedStudySequence[0].RTReferencedSeriesSequence[0]
    assert referenced.SeriesInstanceUID == images[0].SeriesInstanceUID
    assert {i.ReferencedSOPInstanceUID for i in referenced.ContourImageSequence} == {
        s.SOPInstanceUID for s in images
    }


def test_seg_liver_lands_on_liver_density(abdomen_seg: Path, datasets: Path) -> None:
    from miss.structures.labelmap import align_labels

    ct = miss.load_volume(datasets / ABDOMEN / "dicom")
    labels, table = read_seg(abdomen_seg)
    liver = next(n for n, info in table.items() if info.name == "liver")
    aligned = align_labels(labels, ct)
    assert 40 < float(np.asarray(ct.data)[aligned.data == liver].mean()) < 200  # HU


def test_fractional_seg_is_thresholded_at_half(phantom: Path, tmp_path: Path) -> None:
    dims = _grid(phantom / "ct").dims
    values = np.zeros(dims, np.float32)
    values[10:20, 10:20, 2:5] = 0.51  # stored as 130/255: kept
    values[30:40, 10:20, 2:5] = 0.49  # 125/255: dropped
    values[10:20, 30:40, 6:9] = 1.0
    path = write_small_seg(phantom / "ct", tmp_path, {"soft": values}, fractional=True)
    labels, table = read_seg(path)
    assert labels.meta["segmentation_type"] == "FRACTIONAL"
    assert table[1].name == "soft" and table[1].color is None
    assert int(np.count_nonzero(labels.data)) == 2 * 10 * 10 * 3


def test_overlapping_segments_keep_the_higher_number(phantom: Path, tmp_path: Path) -> None:
    dims = _grid(phantom / "ct").dims
    first, second = np.zeros(dims, bool), np.zeros(dims, bool)
    first[5:25, 5:25, 3:6] = True
    second[15:35, 15:35, 3:6] = True
    path = write_small_seg(phantom / "ct", tmp_path, {"first": first, "second": second})
    labels, table = read_seg(path)
    assert [table[1].name, table[2].name] == ["first", "second"]
    assert np.count_nonzero(labels.data == 2) == 20 * 20 * 3
    assert np.count_nonzero(labels.data == 1) == (20 * 20 - 10 * 10) * 3
    assert any("300 voxels in several segments" in note for note in labels.meta["notes"])


def test_seg_grid_is_the_series_grid(phantom: Path, tmp_path: Path) -> None:
    grid = _grid(phantom / "ct")
    mask = np.zeros(grid.dims, bool)
    mask[7, 11, 4] = True
    labels, _ = read_seg(write_small_seg(phantom / "ct", tmp_path, {"dot": mask}))
    (i, j, k), = np.argwhere(labels.data)  # fmt: skip
    mm = labels.affine @ [i, j, k, 1]
    assert np.allclose(mm, grid.affine @ [7, 11, 4, 1], atol=1e-4)


# --------------------------------------------------------------------------- RT-STRUCT


def _outline_tolerance_ml(roi: Roi, grid: Volume) -> float:
    """Half a voxel either side of every outline: perimeter x in-plane step / 2 x slab."""
    dx, dy, dz = grid.spacing
    perimeter = sum(
        float(np.linalg.norm(np.diff(c, axis=0, append=c[:1]), axis=1).sum()) for c in roi.contours
    )
    return perimeter * max(dx, dy) / 2 * dz / 1000


def test_rtstruct_volumes_match_the_analytic_shapes(phantom: Path) -> None:
    grid = _grid(phantom / "ct")
    labels, table = read_rtstruct(phantom / "rt" / "rtstruct.dcm", grid)
    assert labels.dims == grid.dims and np.array_equal(labels.affine, grid.affine)
    assert labels.data.dtype == np.uint16
    voxel_ml = abs(np.linalg.det(grid.affine[:3, :3])) / 1000
    for roi in rtstruct_rois(grid.affine, grid.dims):
        assert table[roi.number].name == roi.name
        assert table[roi.number].color == tuple(c / 255 for c in roi.color)
        ml = np.count_nonzero(labels.data == roi.number) * voxel_ml
        assert abs(ml - roi.ml) <= _outline_tolerance_ml(roi, grid), (roi.name, ml, roi.ml)
    box = rtstruct_rois(grid.affine, grid.dims)[0]
    assert np.count_nonzero(labels.data == 1) * voxel_ml == pytest.approx(box.ml, rel=1e-9)
    # the tube's hole is empty, and its slices are the nearest ones (contours 0.3 up)
    tube = np.argwhere(labels.data == 3)
    centre = np.round(tube[:, :2].mean(axis=0)).astype(int)
    assert labels.data[centre[0], centre[1], 5] == 0
    assert sorted(set(tube[:, 2])) == list(range(2, grid.dims[2] - 2))


def test_polygon_fill_counts_pixel_centres_by_the_even_odd_rule() -> None:
    square = np.array([[1.5, 1.5], [5.5, 1.5], [5.5, 4.5], [1.5, 4.5]])
    assert polygon_mask(square, (8, 8)).sum() == 4 * 3
    star = np.array(
        [[4 + 4 * math.cos(a), 4 + 4 * math.sin(a)] for a in np.arange(5) * 4 * math.pi / 5]
    )
    filled = polygon_mask(star, (9, 9))
    assert not filled[4, 4]  # a pentagram's centre is crossed twice: outside by even-odd
    assert filled.sum() > 0
    # off the grid on every side: clipped, no error
    assert polygon_mask(square + 100, (8, 8)).sum() == 0
    assert polygon_mask(square * 10 - 20, (8, 8)).all()


def test_rtstruct_off_the_grid_or_tilted_is_refused(phantom: Path, tmp_path: Path) -> None:
    grid = _grid(phantom / "ct")
    rois = rtstruct_rois(grid.affine, grid.dims)
    far = [
        Roi(r.number, r.name, r.color, [c + [0, 0, 500.0] for c in r.contours], r.ml) for r in rois
    ]
    path = write_rtstruct(phantom / "ct", tmp_path, far, name="far.dcm")
    with pytest.raises(UnreadableSegmentation, match="no contour covers a voxel centre"):
        read_rtstruct(path, grid)
    tilt = rois[0].contours[0] + np.array([[0, 0, 0], [0, 0, 0], [0, 0, 2.0], [0, 0, 2.0]])
    tilted = [Roi(1, "tilted", (1, 2, 3), [tilt], 0.0)]
    path = write_rtstruct(phantom / "ct", tmp_path, tilted, name="tilted.dcm")
    with pytest.raises(UnreadableSegmentation, match="spans 0.80 slices"):
        read_rtstruct(path, grid)


# --------------------------------------------------------------------------- bad input


def test_sniffing_the_sop_class(phantom: Path, tmp_path: Path) -> None:
    seg = write_small_seg(
        phantom / "ct", tmp_path, {"x": np.ones(_grid(phantom / "ct").dims, bool)}
    )
    (tmp_path / "notes.txt").write_text("not DICOM")
    assert segmentation_kind(seg) == "seg"
    assert segmentation_kind(phantom / "rt" / "rtstruct.dcm") == "rtstruct"
    assert segmentation_kind(phantom / "ct" / "CT001.dcm") is None
    assert segmentation_kind(tmp_path / "notes.txt") is None
    assert segmentation_kind(tmp_path / "missing.dcm") is None


def test_bad_input_gets_errors_that_name_the_fix(phantom: Path, tmp_path: Path) -> None:
    dims = _grid(phantom / "ct").dims
    with pytest.raises(UnreadableSegmentation, match="is not a DICOM SEG .* not one of its images"):
        read_seg(phantom / "ct" / "CT001.dcm")
    with pytest.raises(UnreadableSegmentation, match="it is an RT-STRUCT"):
        read_seg(phantom / "rt" / "rtstruct.dcm")
    with pytest.raises(UnreadableSegmentation, match="is not an RT-STRUCT"):
        read_rtstruct(phantom / "ct" / "CT001.dcm", _grid(phantom / "ct"))
    (tmp_path / "notes.txt").write_text("not DICOM")
    with pytest.raises(UnreadableSegmentation, match="not a readable DICOM file"):
        read_seg(tmp_path / "notes.txt")

    mask = np.zeros(dims, bool)
    mask[10:30, 10:30, :] = True
    good = write_small_seg(phantom / "ct", tmp_path, {"a": mask}, name="good.dcm")
    empty = pydicom.dcmread(good)
    empty.SegmentSequence = []
    empty.save_as(tmp_path / "empty.dcm")
    with pytest.raises(UnreadableSegmentation, match="holds no segments"):
        read_seg(tmp_path / "empty.dcm")

    whole = good.read_bytes()
    for cut in (len(whole) // 2, len(whole) - 100):
        (tmp_path / "cut.dcm").write_bytes(whole[:cut])
        with pytest.raises(UnreadableSegmentation, match="damaged|truncated|export"):
            read_seg(tmp_path / "cut.dcm")


def test_a_seg_too_large_is_refused_before_decoding(
    phantom: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    mask = np.ones(_grid(phantom / "ct").dims, bool)
    path = write_small_seg(phantom / "ct", tmp_path, {"a": mask})
    monkeypatch.setattr(dicom_seg, "MAX_FRAME_PIXELS", 64 * 56 * 11)  # 12 frames in the file
    with pytest.raises(InputTooLarge, match="12 frames of 56 x 64 pixels"):
        read_seg(path)


# --------------------------------------------------------------------------- scene


def test_a_scene_of_all_labels_has_one_named_coloured_part_per_roi(phantom: Path) -> None:
    ct = miss.load_volume(phantom / "ct")
    labels, table = read_rtstruct(phantom / "rt" / "rtstruct.dcm", ct)
    scene = miss.extract_scene(
        ct, label_map=labels, labels="all", table=table, decimate="none", measure=False
    )
    assert [(p.name, p.label) for p in scene.parts] == [("box", 1), ("cylinder", 2), ("tube", 3)]
    for part in scene.parts:
        assert tuple(part.color) == pytest.approx(table[part.label].color)


# --------------------------------------------------------------------------- confined


def _confinements(tmp_path: Path) -> list[confined.Confinement]:
    ways = [confined.Confinement(problem="test: unconfined")]
    if landlockpy.abi_version() >= 1:
        found = confined.probe(tmp_path / "data")
        assert found.confined, found.problem
        ways.append(found)
    return ways


@pytest.mark.slow
def test_the_confined_child_reads_a_seg_and_an_rtstruct(phantom: Path, tmp_path: Path) -> None:
    grid = _grid(phantom / "ct")
    mask = np.zeros(grid.dims, bool)
    mask[10:30, 10:30, 2:8] = True
    seg = write_small_seg(
        phantom / "ct", tmp_path / "made", {"organ": mask}, colors={"organ": (1.0, 0.5, 0.0)}
    )
    for way in _confinements(tmp_path):
        work = tmp_path / "data" / "work"
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        shutil.copy(seg, work / "seg.dcm")
        parsed = confined.parse_upload(
            work, "seg.dcm", way, confined.Limits(seconds=120), mode="segmentation"
        )
        assert parsed.volume is not None and parsed.table_source == "DICOM SEG"
        assert np.count_nonzero(parsed.volume.data) == mask.sum()
        assert parsed.table[0]["name"] == "organ"
        assert parsed.table[0]["color"] == pytest.approx([1.0, 0.5, 0.0], abs=1.01 / 255)

        shutil.rmtree(work)
        shutil.copytree(phantom, work / "unzipped")  # a series and its RT-STRUCT together
        g = {"affine": grid.affine.tolist(), "dims": list(grid.dims)}
        parsed = confined.parse_upload(
            work, "none", way, confined.Limits(seconds=120), mode="segmentation", grid=g
        )
        assert parsed.volume is not None and parsed.table_source == "RT-STRUCT"
        assert [r["name"] for r in parsed.table] == ["box", "cylinder", "tube"]
        assert parsed.volume.dims == grid.dims
        with pytest.raises(BadParameter, match="give the series' grid"):
            confined.parse_upload(
                work, "none", way, confined.Limits(seconds=120), mode="segmentation"
            )


@needs_landlock
def test_the_confined_child_cannot_read_beside_its_folder(phantom: Path, tmp_path: Path) -> None:
    way = confined.probe(tmp_path / "data")
    work = tmp_path / "data" / "work"
    (work / "unzipped").mkdir(parents=True)
    # a folder with no segmentation: the child looks only inside its own folder
    shutil.copy(phantom / "ct" / "CT001.dcm", work / "unzipped")
    with pytest.raises(UnreadableSegmentation, match="no DICOM SEG or RT-STRUCT object found"):
        confined.parse_upload(work, "none", way, confined.Limits(seconds=120), mode="segmentation")
