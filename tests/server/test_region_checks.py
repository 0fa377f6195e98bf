"""The slice range, sample rate and level refused, not swapped nor clamped, by the API
(422) and the command line (exit 2, one line), in the form's own numbering (slices
1-based), with the fix."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

REFUSED = [
    ({"start_slice": 100, "end_slice": 10}, "start_slice 100 is after end_slice 10"),
    ({"start_slice": 0}, "start_slice must be a whole number >= 1 (1-based), got 0"),
    ({"start_slice": 500}, "start_slice 500 is outside 1..128"),
    ({"start_slice": 60, "end_slice": 60}, "slices 60..60 at sample rate 1 leave fewer than 2"),
    ({"start_slice": 60, "end_slice": 61, "sample_rate": 2}, "end_slice of at least 62"),
    ({"sample_rate": "abc"}, "sample_rate"),
    ({"level": 99999}, "level 99999 is outside this volume's values"),
]


@pytest.mark.parametrize(("form", "message"), REFUSED)
def test_the_api_refuses_a_bad_region_with_422(
    client: TestClient, demo_id: str, form: dict[str, Any], message: str
) -> None:
    body = {"volume": demo_id, "level": 300} | form
    r = client.post("/api/models", json=body)
    assert r.status_code == 422, r.text
    detail = str(r.json()["detail"])
    assert message in detail, detail
    assert "59..59" not in detail  # never the 0-based indices of a 1-based form


@pytest.mark.parametrize(("form", "message"), REFUSED[:5])
def test_the_cli_refuses_a_bad_region_in_one_line(
    demo_file: Path, tmp_path: Path, form: dict[str, Any], message: str
) -> None:
    args = [f"--{key.replace('_', '-')}={value}" for key, value in form.items()]
    command = [sys.executable, "-m", "miss.cli", "convert", str(demo_file), "--level", "300"]
    command += ["-o", str(tmp_path / "out.stl"), *args]
    proc = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], proc.stderr
    assert not (tmp_path / "out.stl").exists()
