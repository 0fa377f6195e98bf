"""A job says where it is: each stage (surface, decimation, its check, the files, the error)
reported with a fraction of the whole job that moves within the stage and never goes back."""

from __future__ import annotations

from pathlib import Path

import pytest

from miss.io import load_volume
from miss.pipeline import STAGE_SPANS, run, staged
from miss.spec import JobSpec


def test_a_real_scans_job_reports_its_decimation_as_it_goes(datasets: Path) -> None:
    """The server's default decimation (a guaranteed bound) of the skull-stripped MR."""
    volume = load_volume(datasets / "nifti" / "MR_Gd.nii.gz")
    spec = JobSpec.of(level=245.0, formats=("glb", "stl"))
    heard: list[tuple[str, float]] = []
    run(volume, spec, progress=lambda stage, f: heard.append((stage, f)))
    stages = [s for s, _ in heard]
    assert stages[0] == "surface" and stages[-1] == "done"
    for before, after in (("surface", "decimate"), ("decimate", "write"), ("write", "done")):
        assert stages.index(before) < stages.index(after), stages
    fractions = [f for _, f in heard]
    assert fractions == sorted(fractions)  # the bar never goes back
    lo, hi = STAGE_SPANS["decimate"]
    inside = {f for s, f in heard if s == "decimate" and lo < f < hi}
    assert len(inside) >= 2, heard  # the removal, pass by pass: not one jump
    assert "check" in stages  # the bound is checked, and says so
    assert fractions[-1] == 1.0


def test_stage_fractions_become_the_jobs_and_never_go_back() -> None:
    heard: list[tuple[str, float]] = []
    report = staged(lambda stage, f: heard.append((stage, f)))
    report("surface", 0.5)
    report("decimate", 0.5)
    report("decimate", 0.25)  # a second round starts again: the bar holds
    report("store", 1.0)  # a stage of the worker's own passes as it is
    lo, hi = STAGE_SPANS["decimate"]
    assert heard[1] == ("decimate", pytest.approx(lo + (hi - lo) / 2))
    assert heard[2][1] == heard[1][1]
    assert heard[3] == ("store", 1.0)
