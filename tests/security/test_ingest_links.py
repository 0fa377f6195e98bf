"""``miss ingest`` reads in its own process, unconfined: a symbolic link in the ingested
folder that leads out of it (a detached NRRD's data file, one slice of a DICOM folder)
must not carry another file into the database. Refused in one line, exit 2, nothing
stored; links that stay inside the folder still work."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from server.test_ingest_cli import write_series

DIMS = (8, 6, 5)


def ingest(path: Path, data: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "miss", "ingest", str(path), "--data-dir", str(data)],
        capture_output=True,
        text=True,
        timeout=300,
    )


def stored(data: Path) -> list[Path]:
    return sorted((data / "volumes").glob("*")) if (data / "volumes").is_dir() else []


def detached_nrrd(folder: Path, data_file: str) -> Path:
    """A detached NRRD header in ``folder`` whose voxels are ``data_file``."""
    folder.mkdir(parents=True, exist_ok=True)
    header = folder / "scan.nhdr"
    header.write_text(
        "NRRD0004\ntype: int16\ndimension: 3\n"
        f"sizes: {' '.join(map(str, DIMS))}\nspacings: 1 1 1\nencoding: raw\n"
        f"endian: little\ndata file: {data_file}\n"
    )
    return header


def secret_voxels(path: Path) -> None:
    """A 'secret' that reads as voxels (values 0..239), like any raw file would."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(np.arange(np.prod(DIMS), dtype="<i2").tobytes())


def test_a_detached_data_file_linked_out_of_the_folder_is_refused(tmp_path: Path) -> None:
    secret = tmp_path / "elsewhere" / "secret.raw"
    secret_voxels(secret)
    header = detached_nrrd(tmp_path / "scan", "scan.raw")
    (tmp_path / "scan" / "scan.raw").symlink_to(secret)
    data = tmp_path / "data"
    got = ingest(header, data)
    assert got.returncode == 2, (got.stdout, got.stderr)
    assert got.stderr.startswith("miss: ") and got.stderr.count("\n") == 1, got.stderr
    assert "scan.raw is a symbolic link" in got.stderr and "Traceback" not in got.stderr
    assert stored(data) == [] and got.stdout == ""


def test_a_dicom_slice_linked_out_of_the_folder_is_refused(tmp_path: Path) -> None:
    series = tmp_path / "series"
    write_series(series, 5)
    outside = tmp_path / "outside"
    outside.mkdir()
    os.replace(series / "00004.dcm", outside / "00004.dcm")
    (series / "00004.dcm").symlink_to(outside / "00004.dcm")
    data = tmp_path / "data"
    got = ingest(series, data)
    assert got.returncode == 2, (got.stdout, got.stderr)
    assert "00004.dcm is a symbolic link" in got.stderr and got.stderr.count("\n") == 1
    assert stored(data) == []


def test_a_linked_folder_out_of_the_series_is_refused(tmp_path: Path) -> None:
    series = tmp_path / "series"
    write_series(series, 4)
    elsewhere = tmp_path / "elsewhere"
    write_series(elsewhere, 2)
    (series / "more").symlink_to(elsewhere, target_is_directory=True)
    data = tmp_path / "data"
    got = ingest(series, data)
    assert got.returncode == 2 and "more is a symbolic link" in got.stderr, got.stderr
    assert stored(data) == []


def test_links_inside_the_folder_still_work(tmp_path: Path) -> None:
    folder = tmp_path / "scan"
    secret_voxels(folder / "raw" / "voxels.raw")
    header = detached_nrrd(folder, "scan.raw")
    (folder / "scan.raw").symlink_to(Path("raw") / "voxels.raw")
    data = tmp_path / "data"
    got = ingest(header, data)
    assert got.returncode == 0, got.stderr
    (volume,) = stored(data)
    assert json.loads((volume / "meta.json").read_text())["dims"] == list(DIMS)
