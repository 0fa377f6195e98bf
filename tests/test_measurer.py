"""A fresh process measures in a second process (:mod:`miss.measure.measurer`): numba starts
there while this one works, the figures are the same to the bit, and anything amiss with
that process leaves the measurement to this one."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from miss.decimate import decimate, measured
from miss.measure._jit import deviation
from miss.measure.measurer import Measurer, MeasurerGone
from miss.surface import extract_surface
from miss.types import Mesh, Volume

_CONVERT = """
import json, sys
{before}
from miss.cli import main
main(["convert", {path!r}, "--level", "300", "--schedule", "paper", "--reduce", "0.9",
      "--measure", "--json", "-o", {out!r}])
print(json.dumps({{"numba": "numba" in sys.modules}}))
"""


def _convert(path: Path, out: Path, before: str = "") -> tuple[dict, bool]:
    code = _CONVERT.format(before=before, path=str(path), out=str(out))
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=600, check=True
    )
    stats, loaded = (json.loads(line) for line in proc.stdout.strip().splitlines()[-2:])
    return stats["decimation"], loaded["numba"]


def test_a_fresh_command_measures_in_a_second_process_with_the_same_figures(
    demo_file: Path, tmp_path: Path
) -> None:
    """``miss convert --measure`` (paper schedule) in a fresh process: numba never loads
    there, and the figures are those a process measuring on its own gets (numba loaded
    first: the thread path)."""
    there, numba_here = _convert(demo_file, tmp_path / "a.glb")
    here, numba_loaded = _convert(demo_file, tmp_path / "b.glb", "import miss._numba")
    assert numba_loaded and not numba_here
    assert there["max_error_mm"] is not None and there["max_error_mm"] > 0
    assert (there["max_error_mm"], there["mean_error_mm"]) == (
        here["max_error_mm"],
        here["mean_error_mm"],
    )


@pytest.fixture(scope="module")
def part() -> tuple[Mesh, Mesh, object]:
    """A sphere's surface, decimated unmeasured, and its decimation's report."""
    grid = np.mgrid[-20:21, -20:21, -20:21].astype(np.float32)
    ball = Volume(data=np.sqrt((grid**2).sum(axis=0)), affine=np.eye(4))
    before = extract_surface(ball, 15.0, normals=False)
    after, report = decimate(before, "quadric", 0.9, 0.002, schedule="paper", measure=False)
    return before, after, report


def _local(before: Mesh, after: Mesh) -> tuple[float, float]:
    dev = deviation(before, after, samples=5_000)
    return dev.max_mm, dev.mean_mm


def test_the_second_process_gives_the_local_figures(part: tuple) -> None:
    before, after, report = part
    measurer = Measurer()
    try:
        got = measured(report, before, after, 5_000, measurer.side(before, 5_000))
    finally:
        measurer.close()
    assert (got.max_error_mm, got.mean_error_mm) == _local(before, after)


def test_a_second_process_that_died_leaves_the_measurement_here(part: tuple) -> None:
    before, after, report = part
    measurer = Measurer()
    side = measurer.side(before, 5_000)
    measurer.proc.kill()
    measurer.proc.wait()
    with pytest.raises(MeasurerGone):
        side.deviation(after)
    got = measured(report, before, after, 5_000, side)
    assert (got.max_error_mm, got.mean_error_mm) == _local(before, after)
    measurer.close()


def test_a_second_process_that_answers_nonsense_is_not_believed(part: tuple) -> None:
    """An answer that is not (this part's key, max, mean, samples) is refused, and the
    measurement made here; the measurer is not asked again."""
    before, after, report = part
    measurer = Measurer()
    measurer.proc.kill()
    measurer.proc.wait()
    measurer.proc = subprocess.Popen(
        [sys.executable, "-c",
         "import pickle, sys\n"
         "pickle.dump((0, 'far', 0.0, 1), sys.stdout.buffer); sys.stdout.flush()\n"
         "sys.stdin.buffer.read()"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE,
    )  # fmt: skip
    side = measurer.side(before, 5_000)
    got = measured(report, before, after, 5_000, side)
    assert (got.max_error_mm, got.mean_error_mm) == _local(before, after)
    with pytest.raises(MeasurerGone, match="failed before"):
        measurer.side(before, 5_000).deviation(after)
    measurer.close()
    measurer.proc.wait(timeout=60)
