"""``miss pacs`` and ``miss convert dicomweb:STUDY/SERIES`` as whole processes, against a
real Orthanc."""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import pytest

from pacs.conftest import Series
from pacs.orthanc import Orthanc

GE = "ct_head_dicom_ge_gantrytilt"


def miss(args: list[str], env: dict[str, str], timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "miss.cli", *args],
        capture_output=True, text=True, timeout=timeout, env={**os.environ, **env},
    )  # fmt: skip


@pytest.fixture(scope="module")
def env(orthanc: Orthanc, pacs_series: dict[str, Series]) -> dict[str, str]:
    return orthanc.env("Orthanc")


def test_search_series_get(
    env: dict[str, str], pacs_series: dict[str, Series], tmp_path: Path
) -> None:
    ge = pacs_series[GE]
    out = miss(["pacs", "search", "--patient-id", ge.patient_id, "--json"], env)
    assert out.returncode == 0, out.stderr
    studies = json.loads(out.stdout)["studies"]
    assert [s["study"] for s in studies] == [ge.study]
    table = miss(["pacs", "search", "--patient-name", "doe"], env)
    assert ge.study in table.stdout and "1 study" in table.stdout
    series = miss(["pacs", "series", ge.study], env)
    assert ge.series in series.stdout and "CT" in series.stdout
    got = miss(["pacs", "get", ge.study, ge.series, "-o", str(tmp_path / "series")], env)
    assert got.returncode == 0, got.stderr
    assert len(list((tmp_path / "series").glob("*.dcm"))) == ge.instances


def test_convert_from_the_pacs_and_send_back(
    env: dict[str, str], pacs_series: dict[str, Series], orthanc: Orthanc, tmp_path: Path
) -> None:
    ge = pacs_series[GE]
    stl = tmp_path / "skull.stl"
    source = f"dicomweb:{ge.study}/{ge.series}"
    made = miss(["convert", source, "--level", "300", "-o", str(stl), "--json"], env)
    assert made.returncode == 0, made.stderr
    triangles = json.loads(made.stdout)["triangles"]
    assert struct.unpack_from("<I", stl.read_bytes(), 80)[0] == triangles > 1000
    sent = miss(
        ["pacs", "send", str(stl), "--study", ge.study, "--series", ge.series,
         "--patient-id", ge.patient_id, "--json"], env,
    )  # fmt: skip
    assert sent.returncode == 0, sent.stderr
    uids = json.loads(sent.stdout)["sop_instance_uids"]
    found = orthanc.rest("POST", "/tools/lookup", data=uids[0]).json()
    assert found and found[0]["Type"] == "Instance"
    tags = orthanc.rest("GET", f"/instances/{found[0]['ID']}/simplified-tags").json()
    assert tags["PatientID"] == ge.patient_id and tags["StudyInstanceUID"] == ge.study
    assert tags["FrameOfReferenceUID"] == ge.frame_of_reference
    assert tags["SOPClassUID"] == "1.2.840.10008.5.1.4.1.1.104.3"


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (
            ["convert", "dicomweb:1.2.3", "--level", "300", "-o", "x.stl"],
            "dicomweb:STUDY_UID/SERIES_UID",
        ),
        (["convert", "dicomweb:1.2.3/abc", "--level", "300", "-o", "x.stl"], "is not a DICOM UID"),
        (["pacs", "search", "--study-date", "yesterday"], "study_date must be YYYYMMDD"),
        (["pacs", "send", "nothing.stl", "--study", "1.2.3", "--patient-id", "P"], "nothing.stl"),
    ],
)
def test_bad_input_one_line_exit_2(
    env: dict[str, str], args: list[str], said: str, tmp_path: Path
) -> None:
    out = subprocess.run(
        [sys.executable, "-m", "miss.cli", *args], capture_output=True, text=True,
        timeout=120, env={**os.environ, **env}, cwd=tmp_path,
    )  # fmt: skip
    assert out.returncode == 2, out
    assert said in out.stderr and out.stderr.count("\n") == 1, out.stderr
    assert "Traceback" not in out.stderr


def test_pacs_down_is_one_clear_line(tmp_path: Path) -> None:
    from pacs.orthanc import free_port

    env = {"MISS_PACS_URL": f"http://127.0.0.1:{free_port()}/dicom-web", "MISS_PACS_NAME": "Gone"}
    out = miss(["pacs", "search", "--patient-id", "X"], env)
    assert out.returncode == 2
    assert "cannot reach PACS 'Gone'" in out.stderr and "connection refused" in out.stderr
    assert out.stderr.count("\n") == 1
