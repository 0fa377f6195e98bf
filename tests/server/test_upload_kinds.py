"""Uploads as scans arrive: one .dcm, many .dcm, extension-less DICOM, a MetaImage header
with its data file, and a zip of several series that asks which one to read."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk
from fastapi.testclient import TestClient
from pydicom.uid import generate_uid

from miss.server.volumes.plain import plain_notes

GE = "ct_head_dicom_ge_gantrytilt"
MR = "mr_head_dicom_vsseg001_t1"


def slices(datasets: Path, folder: str, count: int) -> list[Path]:
    """The first ``count`` slice files of a real series (read in place, never copied in)."""
    return sorted((datasets / folder).glob("*.dcm"))[:count]


def post(client: TestClient, files: list[tuple[str, bytes]], **fields: str) -> object:
    parts = [("file", (name, data)) for name, data in files]
    return client.post("/api/volumes", files=parts, data=fields)


def multiframe(datasets: Path, count: int) -> bytes:
    """``count`` MR slices as one multi-frame DICOM file (what some scanners export)."""
    frames = [pydicom.dcmread(p) for p in slices(datasets, MR, count)]
    pixels = np.stack([f.pixel_array for f in frames])
    ds = frames[0]
    ds.NumberOfFrames = count
    ds.PixelData = pixels.tobytes()
    ds.SpacingBetweenSlices = 1.5
    ds.SOPInstanceUID = generate_uid()
    out = io.BytesIO()
    ds.save_as(out)
    return out.getvalue()


@pytest.mark.parametrize("name", ["scan.dcm", "IM000001"])
def test_one_dicom_file_makes_a_volume(client: TestClient, datasets: Path, name: str) -> None:
    r = post(client, [(name, multiframe(datasets, 6))])
    assert r.status_code == 201, r.text
    assert r.json()["dims"] == [512, 512, 6]
    assert r.json()["spacing"] == pytest.approx([0.41015625, 0.41015625, 1.5])


@pytest.mark.parametrize("suffix", [".dcm", ""])
def test_several_dicom_files_make_one_volume(
    client: TestClient, datasets: Path, suffix: str
) -> None:
    files = [(f"IM{k:04d}{suffix}", p.read_bytes()) for k, p in enumerate(slices(datasets, GE, 5))]
    r = post(client, files)
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["modality"] == "CT" and body["series"][0]["slices"] == 5
    assert body["dims"][:2] == [512, 512]


def test_metaimage_header_and_data_file_make_a_volume(client: TestClient, tmp_path: Path) -> None:
    voxels = np.arange(6 * 5 * 4, dtype=np.int16).reshape(4, 5, 6)  # (z, y, x)
    image = sitk.GetImageFromArray(voxels)
    image.SetSpacing((0.5, 0.75, 2.0))
    sitk.WriteImage(image, str(tmp_path / "head.mhd"))
    files = [(p.name, p.read_bytes()) for p in sorted(tmp_path.iterdir())]
    assert [name for name, _ in files] == ["head.mhd", "head.raw"]
    r = post(client, files[::-1])  # the data file first: the order is the browser's
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["dims"] == [6, 5, 4] and body["spacing"] == pytest.approx([0.5, 0.75, 2.0])
    assert body["range"] == [0.0, 119.0]


def two_series_zip(datasets: Path, folder: Path) -> Path:
    """A zip of 3 CT slices and 4 MR slices from two real series, written in ``folder``."""
    path = folder / "two.zip"
    with zipfile.ZipFile(path, "w") as zf:
        for p in slices(datasets, GE, 3):
            zf.write(p, f"ct/{p.name}")
        for p in slices(datasets, MR, 4):
            zf.write(p, f"mr/{p.name}")
    return path


def test_zip_of_two_series_asks_which(client: TestClient, datasets: Path, tmp_path: Path) -> None:
    content = two_series_zip(datasets, tmp_path).read_bytes()
    before = client.get("/api/volumes").json()
    r = post(client, [("two.zip", content)])
    assert r.status_code == 409, r.text
    body = r.json()
    assert "2 series" in body["detail"] and "'series'" in body["detail"]
    found = {(s["modality"], s["slices"]) for s in body["series"]}
    assert found == {("CT", 3), ("MR", 4)}
    assert all(s["uid"].startswith("2.25.") for s in body["series"])  # never the original
    assert client.get("/api/volumes").json() == before  # nothing stored
    ct = next(s for s in body["series"] if s["modality"] == "CT")
    r = post(client, [("two.zip", content)], series=ct["uid"])
    assert r.status_code == 201, r.text
    assert r.json()["modality"] == "CT" and r.json()["units"] == "HU"
    mr = next(s for s in body["series"] if s["modality"] == "MR")
    r = post(client, [("two.zip", content)], series=mr["uid"])
    assert r.status_code == 201, r.text
    assert r.json()["modality"] == "MR" and r.json()["dims"] == [512, 512, 4]


def test_unreadable_upload_is_one_plain_sentence(client: TestClient) -> None:
    r = post(client, [("notes.nii.gz", b"hello, these are my notes\n" * 40)])
    assert r.status_code == 422, r.text
    body = r.json()
    detail, technical = body["detail"], body["technical"]
    assert detail.count("notes.nii.gz") == 1 and "not a NIfTI file" in detail
    assert "byte" not in detail and "magic" not in detail
    assert "magic at byte 344" in technical  # the reader's finding, kept for "more"


def test_a_tilted_series_keeps_its_notes_said_plainly(client: TestClient, datasets: Path) -> None:
    """Issue 42: the GE head CT (gantry tilt 18.5 deg, 28 slices 1.08-7.00 mm apart) keeps
    what its reader changed, in the reader's words and plainly, without file names; the
    slice gap as used (3.894 mm) is given beside the stored step along the stack."""
    files = [(f"IM{k:04d}.dcm", p.read_bytes()) for k, p in enumerate(slices(datasets, GE, 28))]
    r = post(client, files)
    assert r.status_code == 201, r.text
    body = client.get(f"/api/volumes/{r.json()['id']}").json()
    assert len(body["notes"]) == 2 and body["notes"][0].startswith("gantry tilt: ")
    assert body["notes_plain"] == [
        "The scanner's gantry was tilted 18.5°: each slice was placed at its true slant, its "
        "pixels unchanged",
        "The gaps between slices were uneven (1.08 to 7.00 mm): the 28 slices were blended "
        "into 38 evenly spaced slices, 3.894 mm apart",
    ]
    assert body["dims"] == [512, 512, 38]
    assert body["slice_gap"] == pytest.approx(3.894, abs=5e-4)
    assert body["spacing"][2] == pytest.approx(4.106, abs=5e-4)
    assert "IM00" not in str(body["notes"] + body["notes_plain"])


@pytest.mark.parametrize(
    ("note", "plain"),
    [
        (
            "skipped 2 file(s) that are not DICOM images (bytes 0-3 not DICM)",
            "Skipped 2 file(s) that are not DICOM images",
        ),
        (
            "no `space` field: axes taken as LPS-aligned with the spacings",
            "The file did not say which way the patient lies: the usual orientation (LPS) was "
            "assumed",
        ),
        (
            "pydicom: Invalid value for VR UI: [value]",
            "An odd entry in the file's header was passed over (Invalid value for VR UI: [value])",
        ),
    ],
)
def test_other_notes_are_said_plainly(note: str, plain: str) -> None:
    assert plain_notes([note]) == [plain]
