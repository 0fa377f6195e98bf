"""Readers against real scans, synthetic files with known answers, and broken input."""

from __future__ import annotations

import gzip
import zipfile
import zlib
from pathlib import Path

import nibabel as nib
import numpy as np
import pydicom
import pytest
import SimpleITK as sitk

from miss.errors import BadParameter, UnreadableVolume
from miss.io import list_series, load_volume, metaimage, nifti_header, slices
from miss.types import Volume

GANTRY = "ct_head_dicom_ge_gantrytilt"


def link_all(source: Path, target: Path, skip: set[str] = frozenset()) -> Path:
    """Populate ``target`` with symlinks to ``source``'s files (cheap copies of a series)."""
    target.mkdir(parents=True, exist_ok=True)
    for f in source.iterdir():
        if f.name not in skip:
            (target / f.name).symlink_to(f)
    return target


@pytest.fixture(scope="module")
def gantry(datasets: Path) -> Volume:
    return load_volume(datasets / GANTRY)


# ---------------------------------------------------------------- real scans


def test_cthead_detached_slices_big_endian(datasets: Path) -> None:
    folder = datasets / "ct_head_stanford_cthead"
    vol = load_volume(folder / "CThead.nhdr")
    assert vol.dims == (256, 256, 113)
    assert vol.spacing == pytest.approx((1, 1, 2))
    assert vol.value_range() == (0, 3272)
    assert vol.data.dtype == np.int16 and vol.data.dtype.isnative
    assert vol.data.flags.f_contiguous
    # File CThead.57 is slice k=56; each file is rows x columns, so data[i, j] = file[j, i].
    raw = np.fromfile(folder / "CThead.57", dtype=">i2").reshape(256, 256)
    np.testing.assert_array_equal(vol.data[:, :, 56], raw.T)
    assert vol.meta["source_format"] == "nrrd"


def test_gantry_tilt_is_resampled_and_sheared(datasets: Path, gantry: Volume) -> None:
    headers = [
        pydicom.dcmread(f, stop_before_pixels=True) for f in (datasets / GANTRY).glob("*.dcm")
    ]
    z = sorted(float(h.ImagePositionPatient[2]) for h in headers)
    assert gantry.dims[:2] == (512, 512) and gantry.dims[2] > 28  # uneven gaps: resampled
    first = gantry.affine @ [0, 0, 0, 1]
    last = gantry.affine @ [0, 0, gantry.dims[2] - 1, 1]
    assert first[2] == pytest.approx(z[0], abs=1e-3)
    assert last[2] - first[2] == pytest.approx(z[-1] - z[0], abs=1e-3)
    normal = np.cross(gantry.affine[:3, 0], gantry.affine[:3, 1])
    step = gantry.affine[:3, 2]
    tilt = np.degrees(np.arccos(abs(normal @ step) / np.linalg.norm(normal) / np.linalg.norm(step)))
    assert tilt == pytest.approx(18.5, abs=0.1)
    notes = " ".join(gantry.meta["notes"])
    assert "uneven slice gaps" in notes and "gantry tilt" in notes
    assert (gantry.data > 300).sum() > 10_000  # skull
    assert gantry.meta["units"] == "HU" and gantry.meta["modality"] == "CT"


def test_gantry_end_slices_are_the_original_pixels(datasets: Path, gantry: Volume) -> None:
    files = {
        float(pydicom.dcmread(f).ImagePositionPatient[2]): f
        for f in (datasets / GANTRY).glob("*.dcm")
    }
    lowest, highest = pydicom.dcmread(files[min(files)]), pydicom.dcmread(files[max(files)])
    np.testing.assert_array_equal(gantry.data[:, :, 0], lowest.pixel_array.T)
    np.testing.assert_allclose(gantry.data[:, :, -1], highest.pixel_array.T, atol=1e-3)


def test_patient_fields_are_kept_apart(gantry: Volume) -> None:
    assert gantry.patient["PatientID"] == "QMNx85rKkkg"
    assert set(gantry.patient) >= {"PatientName", "PatientBirthDate", "StudyDate"}
    assert not set(gantry.patient) & set(gantry.meta)
    assert gantry.meta["series"][0]["slices"] == 28


def test_jpeg2000_abdomen_decodes(datasets: Path) -> None:
    vol = load_volume(datasets / "ct_abdomen_totalseg" / "dicom")
    assert vol.dims == (512, 512, 20)
    assert vol.value_range() == (-1024, 1839)
    assert vol.data.dtype == np.int16
    assert vol.meta["rescale"] == (1.0, -1024.0)
    assert vol.spacing == pytest.approx((0.9765625, 0.9765625, 2.0))


def test_mr_head_series(datasets: Path) -> None:
    vol = load_volume(datasets / "mr_head_dicom_vsseg001_t1")
    assert vol.dims == (512, 512, 120)
    assert vol.spacing == pytest.approx((0.41015625, 0.41015625, 1.5), abs=1e-6)
    assert vol.value_range() == (0, 1826)
    assert vol.meta["modality"] == "MR" and vol.meta["units"] == ""
    assert vol.meta["notes"] == []
    assert vol.data.flags.f_contiguous


@pytest.mark.parametrize(
    ("name", "dtype"),
    [
        ("nifti/CT_pitch.nii.gz", np.uint8),
        ("nifti/CT_AVM.nii.gz", np.float32),
        ("ct_abdomen_totalseg/example_ct.nii.gz", np.int32),
    ],
)
def test_nifti_affine_is_lps(datasets: Path, name: str, dtype: type) -> None:
    vol = load_volume(datasets / name)
    img = nib.load(datasets / name)
    np.testing.assert_allclose(vol.affine, np.diag([-1, -1, 1, 1]) @ img.affine)
    assert vol.data.dtype == dtype
    np.testing.assert_allclose(vol.data, img.get_fdata(), rtol=1e-6)


def _nibabel_only(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every NIfTI file read through nibabel, as files MISS does not read itself are."""
    monkeypatch.setattr(nifti_header.Declared, "plain", property(lambda self: False))


def _same_volume(a: Volume, b: Volume) -> None:
    assert a.data.dtype == b.data.dtype and a.data.flags.f_contiguous == b.data.flags.f_contiguous
    np.testing.assert_array_equal(a.data, b.data)
    np.testing.assert_array_equal(a.affine, b.affine)
    assert a.meta == b.meta


@pytest.mark.parametrize(
    ("dtype", "endian", "name"),
    [
        (np.int16, ">", "v.nii"),
        (np.uint8, "<", "v.nii.gz"),
        (np.float32, "<", "v.nii"),
        (np.uint16, ">", "v.nii.gz"),
        (np.int64, "<", "v.nii"),
        (np.float64, ">", "v.nii"),
    ],
)
def test_plain_nifti_is_read_as_nibabel_reads_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, dtype: type, endian: str, name: str
) -> None:
    """MISS's own reading of a plain file (one .nii(.gz), an sform, no scaling) gives what
    nibabel gives: voxels, dtype, affine, notes."""
    rng = np.random.default_rng(1)
    data = (rng.random((5, 4, 3)) * 100 - 20).astype(dtype)
    if data.dtype.kind == "f":
        data[0, 0, 0] = np.nan  # replaced by the smallest value, with a note
    affine = np.array([[0, -0.9, 0.1, 40], [1.1, 0, 0, -30], [0, 0.2, 2.5, 7], [0, 0, 0, 1]])
    image = nib.Nifti1Image(data, affine, nib.Nifti1Header(endianness=endian))
    image.header["descrip"] = b"CT head HU"
    nib.save(image, tmp_path / name)
    assert nifti_header.check_header(tmp_path / name).plain
    ours = load_volume(tmp_path / name)
    _nibabel_only(monkeypatch)
    _same_volume(ours, load_volume(tmp_path / name))
    assert ours.meta["units"] == "HU"


@pytest.mark.parametrize(
    "change",
    ["scaled", "qform only", "extension", "zero pixdim", "4-D", "odd offset"],
)
def test_nifti_that_is_not_plain_goes_to_nibabel(tmp_path: Path, change: str) -> None:
    image = nib.Nifti1Image(np.arange(60, dtype=np.int16).reshape(5, 4, 3), np.eye(4))
    header = image.header
    if change == "scaled":
        header.set_slope_inter(2.0, -1.0)
    elif change == "qform only":
        header.set_sform(None, code=0)
        header.set_qform(np.eye(4), code=1)
    elif change == "extension":
        header.extensions.append(nib.nifti1.Nifti1Extension("comment", b"a note"))
    elif change == "zero pixdim":
        header["pixdim"][2] = 0
    elif change == "4-D":
        image = nib.Nifti1Image(np.zeros((5, 4, 3, 1), np.int16), np.eye(4))
    nib.save(image, tmp_path / "v.nii")
    if change == "odd offset":
        raw = bytearray((tmp_path / "v.nii").read_bytes())
        raw[108:112] = np.array([360.0], "<f4").tobytes()  # vox_offset 360: not a multiple of 16
        (tmp_path / "v.nii").write_bytes(bytes(raw[:352] + bytes(8) + raw[352:]))
    assert not nifti_header.check_header(tmp_path / "v.nii").plain
    load_volume(tmp_path / "v.nii")  # nibabel reads it


@pytest.mark.parametrize("name", ["nifti/CT_pitch.nii.gz", "ct_abdomen_totalseg/example_ct.nii.gz"])
def test_real_plain_nifti_as_nibabel_reads_it(
    datasets: Path, monkeypatch: pytest.MonkeyPatch, name: str
) -> None:
    assert nifti_header.check_header(datasets / name).plain
    ours = load_volume(datasets / name)
    _nibabel_only(monkeypatch)
    _same_volume(ours, load_volume(datasets / name))


def test_headsq_space_with_spacings(datasets: Path) -> None:
    vol = load_volume(datasets / "mr_headsq_quarter" / "quarter.nhdr")
    assert vol.dims == (64, 64, 93)
    assert vol.spacing == pytest.approx((3.2, 3.2, 1.5))
    assert vol.value_range() == (0, 3926)
    assert any("mixed `space` with `spacings`" in n for n in vol.meta["notes"])


def test_frogtissue_labels(datasets: Path) -> None:
    path = datasets / "labels_frogtissue" / "frogtissue.mhd"
    vol = load_volume(path)
    assert vol.dims == (500, 470, 136)
    assert vol.spacing == pytest.approx((1, 1, 1.5))
    labels = np.unique(vol.data)
    assert labels[0] == 0 and len(labels) == 26
    # The header under-declares CompressedDataSize; every byte must still be inflated.
    assert any("CompressedDataSize" in n for n in vol.meta["notes"])
    whole = np.frombuffer(zlib.decompress(path.with_suffix(".zraw").read_bytes()), np.uint8)
    np.testing.assert_array_equal(vol.data[:, :, -1], whole.reshape(136, 470, 500)[-1].T)


def test_metaimage_own_parser_matches_simpleitk(tmp_path: Path) -> None:
    image = sitk.GetImageFromArray(np.arange(4 * 3 * 2, dtype=np.int16).reshape(4, 3, 2))
    image.SetSpacing((0.5, 2.0, 3.0))
    image.SetOrigin((1.0, 2.0, 3.0))
    image.SetDirection((0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0))
    sitk.WriteImage(image, str(tmp_path / "v.mhd"), useCompression=True)
    via_itk = load_volume(tmp_path / "v.mhd")
    own = metaimage.read_fallback(tmp_path / "v.mhd")
    np.testing.assert_array_equal(own.data, via_itk.data)
    np.testing.assert_allclose(own.affine, via_itk.affine)
    assert via_itk.affine[:3, 0] == pytest.approx([0.0, -0.5, 0.0])  # i steps along -y (LPS)


def test_dicom_zip_matches_folder(datasets: Path, gantry: Volume, tmp_path: Path) -> None:
    archive = tmp_path / "gantry.zip"
    with zipfile.ZipFile(archive, "w") as z:
        for f in sorted((datasets / GANTRY).glob("*.dcm")):
            z.write(f, f"series/{f.name}")
    vol = load_volume(archive)
    np.testing.assert_array_equal(vol.data, gantry.data)
    np.testing.assert_allclose(vol.affine, gantry.affine)


def test_series_listing_and_choice(datasets: Path, tmp_path: Path) -> None:
    link_all(datasets / GANTRY, tmp_path / "a")
    link_all(datasets / "mr_forearm_dicom_cptac_sar", tmp_path / "b")
    found = list_series(tmp_path)
    assert [s["slices"] for s in found] == [28, 3]
    assert found[1]["dims"] == (512, 512, 3) and found[1]["modality"] == "MR"
    assert load_volume(tmp_path).meta["series_uid"] == found[0]["uid"]
    forearm = load_volume(tmp_path, series=found[1]["uid"])
    assert forearm.dims == (512, 512, 3) and forearm.meta["notes"] == []
    with pytest.raises(BadParameter, match="no series with UID"):
        load_volume(tmp_path, series="1.2.3")


def test_duplicate_slice_is_dropped(datasets: Path, tmp_path: Path) -> None:
    link_all(datasets / GANTRY, tmp_path)
    (tmp_path / "copy-of-05.dcm").symlink_to(datasets / GANTRY / "05.dcm")
    vol = load_volume(tmp_path)
    assert any("dropped 1 slice" in n for n in vol.meta["notes"])


# ------------------------------------------------------ synthetic, known answers


def test_uneven_gaps_interpolate_linearly() -> None:
    positions = np.array([0.0, 1.0, 2.0, 5.0, 6.0])
    origins = np.outer(positions, [0.0, 0.3, 1.0])  # oblique: tilted stack
    stack = np.broadcast_to(positions[:, None, None], (5, 2, 3)).astype(np.int16)
    grid = slices.plan_grid(positions, origins)
    assert grid.resampled and grid.positions.tolist() == [0, 1, 2, 3, 4, 5, 6]
    np.testing.assert_allclose(grid.step, [0, 0.3, 1.0])
    out = slices.resample(stack, positions, grid.positions)
    np.testing.assert_allclose(out[:, 0, 0], grid.positions)  # a linear ramp stays exact


def test_upsampling_cap_falls_back_to_median_gap() -> None:
    positions = np.array([0.0, 0.1, 10.0, 20.0, 30.0])
    grid = slices.plan_grid(positions, np.outer(positions, [0, 0, 1]))
    assert len(grid.positions) <= 4 * len(positions)
    assert "median gap" in grid.notes[-1]


def test_even_gaps_are_kept() -> None:
    positions = np.array([0.0, 1.5, 3.0, 4.5])
    grid = slices.plan_grid(
        positions + 1e-5 * np.array([0, 1, -1, 0]), np.outer(positions, [0, 0, 1])
    )
    assert not grid.resampled and grid.notes == []


def write_nrrd(path: Path, header: str, payload: bytes) -> Path:
    path.write_bytes(("NRRD0004\n" + header + "\n").encode() + payload)
    return path


def test_nrrd_attached_gzip_ras_becomes_lps(tmp_path: Path) -> None:
    values = np.arange(2 * 3 * 4, dtype=">f4")  # fastest axis first: x, then y, then z
    header = (
        "type: float\ndimension: 3\nsizes: 2 3 4\nendian: big\nencoding: gzip\nspace: RAS\n"
        "space directions: (2,0,0) (0,3,0) (0,0,4)\nspace origin: (10,20,30)\n"
    )
    vol = load_volume(write_nrrd(tmp_path / "v.nrrd", header, gzip.compress(values.tobytes())))
    np.testing.assert_array_equal(vol.data, values.reshape(4, 3, 2).transpose(2, 1, 0))
    np.testing.assert_allclose(vol.affine[:3], [[-2, 0, 0, -10], [0, -3, 0, -20], [0, 0, 4, 30]])
    assert vol.meta["notes"] == []


def test_nrrd_written_by_itk_matches_itk(tmp_path: Path) -> None:
    image = sitk.GetImageFromArray(np.arange(5 * 4 * 3, dtype=np.uint16).reshape(5, 4, 3))
    image.SetSpacing((0.7, 0.8, 2.5))
    image.SetOrigin((-10.0, 5.0, 40.0))
    c, s = np.cos(0.3), np.sin(0.3)
    image.SetDirection((c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0))
    sitk.WriteImage(image, str(tmp_path / "v.nrrd"), useCompression=True)
    vol = load_volume(tmp_path / "v.nrrd")
    assert vol.meta["source_format"] == "nrrd"
    np.testing.assert_array_equal(vol.data, sitk.GetArrayFromImage(image).transpose(2, 1, 0))
    expected = np.eye(4)
    expected[:3, :3] = np.array(image.GetDirection()).reshape(3, 3) * image.GetSpacing()
    expected[:3, 3] = image.GetOrigin()
    np.testing.assert_allclose(vol.affine, expected, atol=1e-9)


def test_nrrd_detached_list(tmp_path: Path) -> None:
    for k in range(3):
        (tmp_path / f"s{k}.raw").write_bytes(np.full((2, 2), k, dtype="<u2").tobytes())
    header = "type: ushort\ndimension: 3\nsizes: 2 2 3\nendian: little\nencoding: raw\nspacings: 1 1 5\ndata file: LIST\ns0.raw\ns1.raw\ns2.raw"
    vol = load_volume(write_nrrd(tmp_path / "v.nhdr", header, b""))
    assert vol.data[0, 0, :].tolist() == [0, 1, 2]
    assert vol.spacing == pytest.approx((1, 1, 5))
    assert any("no `space` field" in n for n in vol.meta["notes"])


def test_nifti_nan_and_4d(tmp_path: Path) -> None:
    data = np.ones((3, 4, 5, 2), dtype=np.float32)
    data[0, 0, 0, 0] = np.nan
    data[1, 1, 1, 0] = -7
    nib.save(nib.Nifti1Image(data, np.eye(4)), tmp_path / "v.nii")
    vol = load_volume(tmp_path / "v.nii")
    assert vol.dims == (3, 4, 5) and vol.data[0, 0, 0] == -7
    notes = " ".join(vol.meta["notes"])
    assert "first volume" in notes and "NaN" in notes


# ---------------------------------------------------------------- broken input


def test_missing_path(tmp_path: Path) -> None:
    with pytest.raises(UnreadableVolume, match="no such file or folder"):
        load_volume(tmp_path / "nothing.nii.gz")


def test_empty_file(tmp_path: Path) -> None:
    (tmp_path / "empty.nrrd").touch()
    with pytest.raises(UnreadableVolume, match=r"empty \(0 bytes\)"):
        load_volume(tmp_path / "empty.nrrd")


def test_truncated_nifti_gzip(datasets: Path, tmp_path: Path) -> None:
    whole = (datasets / "nifti" / "CT_pitch.nii.gz").read_bytes()
    (tmp_path / "cut.nii.gz").write_bytes(whole[: len(whole) // 2])
    with pytest.raises(UnreadableVolume, match="cut.nii.gz: the file is truncated"):
        load_volume(tmp_path / "cut.nii.gz")


def test_wrong_magic(tmp_path: Path) -> None:
    (tmp_path / "noise.nii").write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(UnreadableVolume, match="noise.nii: not a NIfTI file"):
        load_volume(tmp_path / "noise.nii")


def test_nrrd_missing_data_file(datasets: Path, tmp_path: Path) -> None:
    link_all(datasets / "ct_head_stanford_cthead", tmp_path, skip={"CThead.57"})
    with pytest.raises(
        UnreadableVolume,
        match=r"data file CThead\.57 is missing; the header lists CThead\.1\.\.113",
    ):
        load_volume(tmp_path / "CThead.nhdr")


def test_nrrd_truncated_data(tmp_path: Path) -> None:
    path = write_nrrd(
        tmp_path / "v.nrrd",
        "type: short\ndimension: 3\nsizes: 4 4 4\nendian: little\nencoding: raw\n",
        b"\0" * 100,
    )
    with pytest.raises(UnreadableVolume, match="truncated: v.nrrd holds 100 of the 128 bytes"):
        load_volume(path)


def test_single_slice_dicom(datasets: Path, tmp_path: Path) -> None:
    link_all(datasets / GANTRY, tmp_path, skip={f"{k:02d}.dcm" for k in range(2, 29)})
    with pytest.raises(UnreadableVolume, match="only 1 slice; a surface needs at least 2 slices"):
        load_volume(tmp_path)


def test_zip_with_parent_member(tmp_path: Path) -> None:
    with zipfile.ZipFile(tmp_path / "evil.zip", "w") as z:
        z.writestr("../escape.dcm", b"\0" * 200)
    with pytest.raises(UnreadableVolume, match="refusing member '../escape.dcm'"):
        load_volume(tmp_path / "evil.zip")


def test_folder_of_other_format_points_at_the_file(datasets: Path) -> None:
    with pytest.raises(UnreadableVolume, match="pass that file instead"):
        load_volume(datasets / "mr_headsq_quarter")


def test_nifti_ct_is_recognised_as_hu(datasets: Path, tmp_path: Path) -> None:
    """NIfTI has no modality; air near -1000 marks CT so HU presets apply, MR stays unitless."""
    ct = load_volume(datasets / "ct_abdomen_totalseg" / "example_ct.nii.gz")
    assert (ct.meta["modality"], ct.meta["units"]) == ("CT", "HU")
    mr = load_volume(datasets / "nifti" / "MR_Gd.nii.gz")
    assert mr.meta["units"] != "HU"


def test_a_resource_warning_during_a_read_is_no_note_of_the_scan() -> None:
    """The garbage collector's ResourceWarning about some unrelated object (a socket left
    unclosed elsewhere) can come while a reader runs: it is passed on, not made a note."""
    import warnings

    from miss.io.common import recorded_warnings

    with pytest.warns(ResourceWarning), recorded_warnings("pydicom") as notes:
        warnings.warn("unclosed <socket.socket fd=15>", ResourceWarning, stacklevel=1)
        warnings.warn("Invalid value for VR UI", UserWarning, stacklevel=1)
    assert notes == ["pydicom: Invalid value for VR UI"]
