"""``miss ingest PATH``: a big gzipped NIfTI stored with far less memory than its voxels
take, listed and served by the server like an upload; bad input is one line, exit 2."""

from __future__ import annotations

import gzip
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from support import ADMIN_PASSWORD
from support.pg import settings_for

from miss.server.app import create_app
from miss.server.storage import chunked

SHAPE = (512, 512, 1600)  # int16: 839 MB of voxels
#: Runs ``miss ingest`` and prints its exit code and peak RSS (kB): this process's only
#: child, so RUSAGE_CHILDREN is that command alone.
PEAK = """
import json, resource, subprocess, sys
run = subprocess.run([sys.executable, "-m", "miss", "ingest", *sys.argv[1:]],
                     capture_output=True, text=True)
peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
print(json.dumps({"rc": run.returncode, "out": run.stdout, "err": run.stderr, "peak_kb": peak}))
"""


def plane(k: int) -> np.ndarray:
    """Slice ``k`` of a CT-like cylinder in air that grows along z, (X, Y) int16."""
    i, j = np.indices(SHAPE[:2])
    inside = (i - 256) ** 2 + (j - 256) ** 2 < (100 + k // 12) ** 2
    return np.where(inside, 1040 + k % 7, -1000).astype(np.int16)


@pytest.fixture(scope="module")
def big_nifti(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A plain NIfTI-1 .nii.gz of SHAPE, written slice by slice (never whole here either)."""
    import nibabel as nib

    header = nib.Nifti1Header()
    header.set_data_shape(SHAPE)
    header.set_data_dtype(np.int16)
    header.set_sform(np.diag([0.7, 0.7, 0.5, 1.0]), code=1)
    header.set_qform(np.diag([0.7, 0.7, 0.5, 1.0]), code=1)
    header["vox_offset"] = 352
    path = tmp_path_factory.mktemp("big") / "big_ct.nii.gz"
    with gzip.open(path, "wb", compresslevel=1) as out:
        out.write(header.binaryblock + b"\0" * 4)
        for k in range(SHAPE[2]):
            out.write(plane(k).tobytes(order="F"))
    return path


def ingest(*args: str) -> dict:
    proc = subprocess.run(
        [sys.executable, "-c", PEAK, *args], capture_output=True, text=True, timeout=900
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


@pytest.mark.slow
def test_ingest_of_a_big_gzipped_nifti_stays_far_under_its_size(
    big_nifti: Path, tmp_path: Path
) -> None:
    data = tmp_path / "data"
    got = ingest(str(big_nifti), "--data-dir", str(data), "--name", "Big CT")
    assert got["rc"] == 0, got["err"]
    volume_id = got["out"].strip()
    size = int(np.prod(SHAPE)) * 2
    peak = got["peak_kb"] * 1024
    print(f"peak RSS {peak / 2**20:.0f} MB for {size / 2**20:.0f} MB of voxels")
    assert peak < size / 2, f"peak RSS {peak / 2**20:.0f} MB, voxels {size / 2**20:.0f} MB"

    stored = chunked.open_array(data / "volumes" / volume_id / "data.zarr")[0]
    for k in (0, 799, 1599):
        assert np.array_equal(stored[:, :, k], plane(k)), k
    client = TestClient(create_app(settings_for(data, admin_password=ADMIN_PASSWORD, demo=False)))
    with client:
        r = client.post("/api/auth/login", json={"username": "admin", "password": ADMIN_PASSWORD})
        client.headers["Authorization"] = f"Bearer {r.json()['token']}"
        client.cookies.clear()
        (listed,) = client.get("/api/volumes").json()
        assert listed["id"] == volume_id and listed["name"] == "Big CT"
        assert listed["dims"] == list(SHAPE) and listed["modality"] == "CT"
        assert listed["range"] == [-1000.0, 1046.0]
        r = client.get(f"/api/volumes/{volume_id}/slices/sagittal/256.png")
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"


@pytest.mark.slow  # two `miss ingest` processes
def test_ingest_errors_are_one_line_and_leave_nothing(tmp_path: Path) -> None:
    data = tmp_path / "data"
    broken = tmp_path / "broken.nii.gz"
    whole = gzip.compress(b"\0" * 400)
    broken.write_bytes(whole[: len(whole) // 2])
    for path in (tmp_path / "missing.nii", broken):
        got = ingest(str(path), "--data-dir", str(data))
        assert got["rc"] == 2 and got["out"] == "", got
        assert got["err"].startswith("miss: ") and got["err"].count("\n") == 1, got["err"]
    assert not list((data / "volumes").glob("*"))
    assert not list((data / "tmp").glob("*"))


#: A long synthetic DICOM series: 512 x 512 x 1600 int16, 839 MB of voxels.
DICOM_SLICES = 1600


def write_series(folder: Path, slices: int) -> None:
    """One CT series, a slice per file, ``plane(k)`` at z = 0.5 k mm (written one by one)."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

    folder.mkdir()
    study, series = generate_uid(), generate_uid()
    for k in range(slices):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = (
            CTImageStorage,
            generate_uid(),
        )
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID, ds.SOPInstanceUID = CTImageStorage, meta.MediaStorageSOPInstanceUID
        ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.Modality = study, series, "CT"
        ds.PatientName, ds.PatientID = "Doe^Jane", "PID-1234"
        ds.ImagePositionPatient, ds.ImageOrientationPatient = [0, 0, 0.5 * k], [1, 0, 0, 0, 1, 0]
        ds.PixelSpacing, ds.InstanceNumber = [0.7, 0.7], k + 1
        ds.Rows, ds.Columns, ds.SamplesPerPixel = SHAPE[1], SHAPE[0], 1
        ds.PhotometricInterpretation, ds.BitsAllocated, ds.BitsStored = "MONOCHROME2", 16, 16
        ds.HighBit, ds.PixelRepresentation = 15, 1
        ds.RescaleSlope, ds.RescaleIntercept = 1, 0
        ds.PixelData = np.ascontiguousarray(plane(k).T).tobytes()  # rows (y) of columns (x)
        ds.save_as(folder / f"{k:05d}.dcm", enforce_file_format=True)


@pytest.mark.slow
def test_ingest_of_a_long_dicom_series_stays_far_under_its_size(tmp_path: Path) -> None:
    """A folder of slices is decoded one slice at a time (twice: the value range picks the
    dtype first), never stacked whole; the patient goes to the owner-only record."""
    series = tmp_path / "series"
    write_series(series, DICOM_SLICES)
    data = tmp_path / "data"
    got = ingest(str(series), "--data-dir", str(data))
    assert got["rc"] == 0, got["err"]
    volume_id = got["out"].strip()
    size = SHAPE[0] * SHAPE[1] * DICOM_SLICES * 2
    peak = got["peak_kb"] * 1024
    print(f"peak RSS {peak / 2**20:.0f} MB for {size / 2**20:.0f} MB of voxels")
    assert peak < size / 2, f"peak RSS {peak / 2**20:.0f} MB, voxels {size / 2**20:.0f} MB"
    folder = data / "volumes" / volume_id
    stored = chunked.open_array(folder / "data.zarr")[0]
    assert stored.shape == (*SHAPE[:2], DICOM_SLICES) and stored.dtype == np.int16
    for k in (0, 601, DICOM_SLICES - 1):
        assert np.array_equal(stored[:, :, k], plane(k)), k
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["modality"] == "CT" and meta["units"] == "HU"
    assert "Doe" not in (folder / "meta.json").read_text()


@pytest.mark.parametrize("name", ["mr_head_dicom_vsseg001_t1", "ct_abdomen_totalseg/dicom"])
def test_a_streamed_series_is_the_series_read_whole(name: str, datasets: Path) -> None:
    """Plane by plane or whole: the same voxels, dtype, affine, metadata and patient."""
    from miss.io import dicom

    folder = datasets / name
    whole = dicom.read(folder, None)
    streamed = dicom.stream(folder)
    assert streamed is not None
    planes = np.stack(list(streamed.planes), axis=2)
    assert planes.dtype == whole.data.dtype and np.array_equal(planes, whole.data)
    assert np.array_equal(streamed.affine, whole.affine)
    assert streamed.meta(0.0, 0.0) == whole.meta and streamed.patient == whole.patient


def test_a_series_with_uneven_gaps_is_read_whole(datasets: Path) -> None:
    """Resampling onto a regular grid needs neighbouring slices: no stream, a whole read."""
    from miss.io import dicom

    folder = datasets / "ct_head_dicom_ge_gantrytilt"
    assert dicom.stream(folder) is None
