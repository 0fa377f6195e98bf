"""Uploads are read and stored plane by plane (the confined child writes its answer one
plane at a time, the server stores it from that file one plane at a time), and what is
stored is what reading the scan whole and storing it gives."""

from __future__ import annotations

import json
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import psutil
import pytest
from fastapi.testclient import TestClient
from support.realserver import serving

from miss.deid import deidentify
from miss.io import load_volume
from miss.io.confined import _jsonable
from miss.server.storage import chunked
from miss.server.storage.store import Store
from miss.server.volumes.ingest import UID_KEY, check_storable, stage
from miss.types import Volume

#: Streamed in the child (a DICOM folder, plain NIfTI-1) and read whole there (gantry
#: tilt with uneven gaps, a scaled NIfTI): the server stores both from planes.
SCANS = [
    "mr_head_dicom_vsseg001_t1",
    "ct_head_dicom_ge_gantrytilt",
    "nifti/CT_pitch.nii.gz",
    "ct_abdomen_totalseg/example_ct.nii.gz",
    "nifti/CT_AVM.nii.gz",
]


def as_upload(scan: Path, tmp_path: Path) -> Path:
    """A file as uploaded: a folder of slices zipped inside a folder, a file as it is."""
    if scan.is_file():
        return scan
    path = tmp_path / f"{scan.name}.zip"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
        for f in sorted(scan.iterdir()):
            zf.write(f, f"series/{f.name}")
    return path


def whole_read(store: Store, scan: Path) -> tuple[Path, dict, dict]:
    """What the upload stored before it streamed: ``load_volume`` whole, its metadata and
    patient through JSON (as the child sent them), checked, de-identified, ``stage``d;
    (folder, info, identity)."""
    volume = load_volume(scan)
    described = _jsonable({"meta": volume.meta, "patient": volume.patient})
    volume = Volume(volume.data, volume.affine, described["meta"], described["patient"])
    check_storable(volume, scan.name)
    clean = deidentify(volume, store.secret(UID_KEY))
    folder, info = stage(store, clean.volume, clean.report)
    return folder, info, clean.identity


@pytest.mark.parametrize("name", SCANS)
def test_an_upload_stores_what_the_whole_read_stored(
    client: TestClient, datasets: Path, tmp_path: Path, name: str
) -> None:
    scan = datasets / name
    upload = as_upload(scan, tmp_path)
    with upload.open("rb") as f:
        r = client.post("/api/volumes", files={"file": (upload.name, f)})
    assert r.status_code == 201, r.text
    volume_id = r.json()["id"]
    store: Store = client.app.state.store
    got = store.data_dir / "volumes" / volume_id
    folder, info, identity = whole_read(store, scan)

    stored, expected = (
        chunked.open_array(got / "data.zarr"),
        chunked.open_array(folder / "data.zarr"),
    )
    assert stored[0].dtype == expected[0].dtype and stored[0].shape == expected[0].shape
    assert np.array_equal(stored[0][:, :, :], expected[0][:, :, :])
    assert np.array_equal(stored[1], expected[1]) and stored[2] == expected[2]
    assert json.loads((got / "meta.json").read_text()) == info
    for file in ("histogram.json", "thumbnail.png"):
        assert (got / file).read_bytes() == (folder / file).read_bytes(), file
    row = store.get_identity(volume_id)  # the file name is kept for the owner, always
    assert row is not None and row.data == identity | {"upload_filename": upload.name}
    assert not list((store.data_dir / "tmp").glob("*/out/data.npy"))


#: A plain NIfTI-1 of 512 x 512 x 1400 int16: 734 MB of voxels.
SHAPE = (512, 512, 1400)


def plane(k: int) -> np.ndarray:
    """Slice ``k``: a CT-like cylinder in air that grows along z, (X, Y) int16."""
    i, j = np.indices(SHAPE[:2])
    inside = (i - 256) ** 2 + (j - 256) ** 2 < (100 + k // 12) ** 2
    return np.where(inside, 1040 + k % 7, -1000).astype(np.int16)


def write_nifti(path: Path) -> None:
    """A plain (uncompressed) NIfTI-1 of SHAPE, written slice by slice."""
    import nibabel as nib

    header = nib.Nifti1Header()
    header.set_data_shape(SHAPE)
    header.set_data_dtype(np.int16)
    header.set_sform(np.diag([0.7, 0.7, 0.5, 1.0]), code=1)
    header["vox_offset"] = 352
    with path.open("wb") as out:
        out.write(header.binaryblock + b"\0" * 4)
        for k in range(SHAPE[2]):
            out.write(plane(k).tobytes(order="F"))


class Peaks:
    """Peak resident memory (VmHWM) of a server and of each confined reader it starts,
    sampled from outside every 20 ms until ``stop``."""

    def __init__(self, server_pid: int) -> None:
        self.server = psutil.Process(server_pid)
        self.before = hwm(server_pid)  # started, logged in: its imports and caches
        self.child = 0
        self.children: set[int] = set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        while not self._stop.is_set():
            for proc in self.server.children(recursive=True):
                try:
                    if "confined" in " ".join(proc.cmdline()):
                        self.children.add(proc.pid)
                        self.child = max(self.child, hwm(proc.pid))
                except (psutil.Error, OSError):
                    pass
            time.sleep(0.02)

    def stop(self) -> int:
        """Stop sampling; the server's own peak so far (bytes)."""
        self._stop.set()
        self._thread.join()
        return hwm(self.server.pid)


def hwm(pid: int) -> int:
    """``VmHWM`` of ``pid`` (bytes): the most resident memory it has had."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise OSError(f"no VmHWM for {pid}")


def test_a_big_upload_stays_far_under_its_size_in_the_server_and_its_reader(
    tmp_path: Path,
) -> None:
    """The server and the confined reader each hold a few planes, not the volume."""
    path = tmp_path / "big_ct.nii"
    write_nifti(path)
    size = int(np.prod(SHAPE)) * 2
    with serving(tmp_path / "data", tmp_path / "server.log") as server:
        peaks = Peaks(server.proc.pid)
        with path.open("rb") as f:
            r = server.http.post("/api/volumes", files={"file": (path.name, f)}, timeout=900)
        server_peak = peaks.stop()
        assert r.status_code == 201, r.text
        body = r.json()
        assert body["dims"] == list(SHAPE) and body["range"] == [-1000.0, 1046.0]
        stored = chunked.open_array(tmp_path / "data" / "volumes" / body["id"] / "data.zarr")
        for k in (0, 701, SHAPE[2] - 1):
            assert np.array_equal(stored[0][:, :, k], plane(k)), k
    mb = 2**20
    print(
        f"voxels {size / mb:.0f} MB; peak RSS: server {server_peak / mb:.0f} MB "
        f"({peaks.before / mb:.0f} MB before the upload), reader {peaks.child / mb:.0f} MB"
    )
    assert peaks.children, "no confined reader was seen"
    assert server_peak < size / 2, f"server {server_peak / mb:.0f} MB"
    assert server_peak - peaks.before < size / 4, f"server {server_peak / mb:.0f} MB"
    assert peaks.child < size / 2, f"reader {peaks.child / mb:.0f} MB"
