"""Every bad-input corpus case through ``load_volume`` and ``miss info``.

Each case either loads (finite voxels, a non-degenerate affine) or is refused with a
``MissError`` whose one-line message names the file, the problem and a fix; any other
exception, a traceback, a stray line on stderr or an allocation the header made up is a
failure. The corpus is written from code (tests/corpus) into a temporary folder.
"""

from __future__ import annotations

import atexit
import importlib.util
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from corpus.cases import generate
from corpus.checks import message_problems, volume_problems

from miss.errors import MissError
from miss.io import itk, load_volume

#: Written once at collection, so that the cases can parametrize the tests by name.
CORPUS_DIR = Path(tempfile.mkdtemp(prefix="miss-corpus-"))
atexit.register(shutil.rmtree, CORPUS_DIR, ignore_errors=True)
CASES = {case.name: case for case in generate(CORPUS_DIR)}


@pytest.mark.parametrize("name", sorted(CASES))
def test_load_volume_loads_or_refuses_clearly(name: str) -> None:
    case = CASES[name]
    try:
        vol = load_volume(case.path)
    except MissError as exc:
        assert case.expect == "error", f"{name} should load ({case.why}), but: {exc}"
        assert message_problems(str(exc), case.path.name) == [], str(exc)
        return
    assert case.expect == "ok", f"{name} should be refused ({case.why}); it loaded {vol.dims}"
    assert volume_problems(vol) == []


# ------------------------------------------------------------------ the command line

#: Runs ``miss info`` in-process on every path given, with file descriptor 2 redirected
#: per case so that what C++ libraries print is caught too; one JSON line per case.
INFO_ALL = r"""
import json, os, sys, tempfile
from miss.cli import main
for path in sys.argv[1:]:
    with tempfile.TemporaryFile() as err:
        sys.stdout.flush(); sys.stderr.flush()
        saved_out, saved_err = os.dup(1), os.dup(2)
        os.dup2(err.fileno(), 2); os.dup2(os.open(os.devnull, os.O_WRONLY), 1)
        escaped = ""
        try:
            code = main(["info", path])
        except BaseException as exc:
            code, escaped = None, type(exc).__name__
        sys.stdout.flush(); sys.stderr.flush()
        os.dup2(saved_out, 1); os.dup2(saved_err, 2)
        err.seek(0)
        text = err.read().decode("utf-8", "replace")
    print(json.dumps({"path": path, "code": code, "stderr": text, "escaped": escaped}), flush=True)
"""


def test_cli_info_on_every_case_exits_0_or_2_with_one_line() -> None:
    """All cases in one process (fast); ``main`` is what the ``miss`` entry point runs."""
    paths = [str(case.path) for case in CASES.values()]
    proc = subprocess.run(
        [sys.executable, "-c", INFO_ALL, *paths], capture_output=True, encoding="utf-8", timeout=900
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = {r["path"]: r for r in map(json.loads, proc.stdout.splitlines())}
    failures = []
    for case in CASES.values():
        r = results[str(case.path)]
        lines = r["stderr"].strip().splitlines()
        expected = 0 if case.expect == "ok" else 2
        if r["escaped"] or r["code"] != expected:
            failures.append(f"{case.name}: exit {r['code']} {r['escaped']} {lines}")
        elif expected == 2 and (len(lines) != 1 or "Traceback" in r["stderr"]):
            failures.append(f"{case.name}: stderr is not one line: {lines}")
        elif expected == 0 and lines:
            failures.append(f"{case.name}: loaded but printed on stderr: {lines}")
    assert failures == []


@pytest.mark.parametrize(
    "name",
    [
        "nifti-absurd-dims-gz",
        "zip-bomb-ratio",
        "dicom-nan-position",
        "nrrd-data-file-absolute",
        "mha-ndims-huge",
        "dicom-non-utf8-name-damaged",
        "random-no-extension",
    ],
)
def test_cli_process_one_line_exit_2(name: str) -> None:
    """The real process, for a few cases: exit code 2, one line, no traceback."""
    case = CASES[name]
    proc = subprocess.run(
        [sys.executable, "-m", "miss.cli", "info", str(case.path)],
        capture_output=True,
        encoding="utf-8",
        timeout=300,
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("miss: "), proc.stderr
    assert "Traceback" not in proc.stderr


# ------------------------------------------------------------------ memory

#: Loads each path under an address-space limit of what the process already maps plus
#: HEADROOM bytes (the imports alone map ~1.2 GB): a reader that allocates what a header
#: claims, or inflates a bomb, gets MemoryError instead of taking the machine down.
LIMITED = r"""
import json, resource, sys
from miss.errors import MissError
from miss.io import load_volume
headroom = int(sys.argv[1])
with open("/proc/self/status") as status:
    mapped = int(status.read().split("VmSize:")[1].split()[0]) * 1024
resource.setrlimit(resource.RLIMIT_AS, (mapped + headroom, mapped + headroom))
for path in sys.argv[2:]:
    try:
        vol = load_volume(path)
        out = {"result": "loaded", "dims": list(vol.dims)}
    except MissError as exc:
        out = {"result": type(exc).__name__, "message": str(exc)}
    except BaseException as exc:
        out = {"result": "crash " + type(exc).__name__, "message": str(exc)}
    print(json.dumps(out), flush=True)
"""
HEADROOM = 512 * 1024**2
#: Headers that declare far more than memory, and payloads that inflate far beyond it.
HUNGRY = [
    "nifti-absurd-dims",
    "nifti-absurd-dims-gz",
    "nifti2-absurd-dims",
    "nrrd-sizes-absurd-gzip",
    "nrrd-gzip-trailing-bomb",
    "mha-compressed-absurd",
    "mha-dimsize-absurd",
    "vtk-absurd-dims",
    "dicom-rows-columns-absurd",
    "dicom-position-outlier",
    "zip-bomb-ratio",
    "zip-bomb-declared-huge",
]


def test_absurd_sizes_are_refused_without_allocating() -> None:
    paths = [str(CASES[name].path) for name in HUNGRY]
    proc = subprocess.run(
        [sys.executable, "-c", LIMITED, str(HEADROOM), *paths],
        capture_output=True,
        encoding="utf-8",
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    outcomes = [json.loads(line) for line in proc.stdout.splitlines()]
    assert len(outcomes) == len(HUNGRY), proc.stderr[-3000:]
    for name, out in zip(HUNGRY, outcomes, strict=True):
        expected = "loaded" if CASES[name].expect == "ok" else "UnreadableVolume"
        assert out["result"] == expected, (name, out)
        assert "memory" not in out.get("message", ""), (name, out)


# ------------------------------------------------------------------ the corpus itself


def test_corpus_is_well_formed() -> None:
    kinds = {"dicom", "nifti", "nrrd", "mha", "zip", "other"}
    for name, case in CASES.items():
        assert re.fullmatch(r"[a-z0-9]+(-[a-z0-9]+)*", name), name
        assert case.kind in kinds and case.expect in ("ok", "error") and case.why, name
        assert case.path.exists() and CORPUS_DIR in case.path.parents, name
    assert len(CASES) >= 150
    assert {c.kind for c in CASES.values()} == kinds
    # The 1 GiB zip bomb is written without 1 GiB on disk.
    assert CASES["zip-bomb-ratio"].path.stat().st_size < 4 * 1024**2


def test_corpus_loads_by_path_and_runs_as_a_script(tmp_path: Path) -> None:
    """How benchmarks/robustness.py and other helpers use it, without ``tests`` on sys.path."""
    script = Path(__file__).parent / "corpus" / "cases.py"
    spec = importlib.util.spec_from_file_location("corpus_cases_by_path", script)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    names = [c.name for c in module.generate(tmp_path / "by-path")]
    assert names == list(CASES)
    proc = subprocess.run(
        [sys.executable, str(script), str(tmp_path / "script")],
        capture_output=True,
        encoding="utf-8",
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert len(proc.stdout.splitlines()) == len(CASES)


# ------------------------------------------------------------------ good data unchanged


@pytest.mark.parametrize(
    ("suffix", "dtype", "components", "compressed"),
    [
        (".mha", "int16", 1, False),
        (".mha", "int16", 1, True),
        (".mhd", "uint8", 1, False),
        (".mhd", "float32", 1, True),
        (".mha", "int32", 2, False),
        (".mhd", "uint16", 3, True),
    ],
)
def test_metaimage_read_by_miss_matches_simpleitk(
    tmp_path: Path, suffix: str, dtype: str, components: int, compressed: bool
) -> None:
    """MetaImage is now read by MISS's parser (SimpleITK hangs or crashes on hostile
    headers): what SimpleITK writes must come back exactly as SimpleITK reads it."""
    shape = (5, 4, 3) + ((components,) if components > 1 else ())
    values = np.random.default_rng(0).integers(0, 100, shape).astype(dtype)
    image = sitk.GetImageFromArray(values, isVector=components > 1)
    image.SetSpacing((0.5, 2.0, 3.0))
    image.SetOrigin((1.0, -2.0, 3.5))
    c, s = np.cos(0.4), np.sin(0.4)
    image.SetDirection((c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0))
    path = tmp_path / f"v{suffix}"
    sitk.WriteImage(image, str(path), useCompression=compressed)
    ours = load_volume(path)
    theirs = itk.to_volume(path, itk.read_image(path), "metaimage")
    assert ours.data.dtype == theirs.data.dtype
    np.testing.assert_array_equal(ours.data, theirs.data)
    np.testing.assert_allclose(ours.affine, theirs.affine)
