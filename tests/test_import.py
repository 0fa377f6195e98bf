"""``import miss`` in a program loads what the API's calls use, so their first call does
not pay for it; the ``miss`` command, MISS's modules run as programs and the processes MISS
starts (``MISS_LEAN_IMPORT=1``) load what they need on first use. The documented functions
keep their names (``miss.decimate`` and ``miss.export`` are functions)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

HEAVY = ["vtk", "numba", "meshoptimizer", "pydicom", "SimpleITK", "nibabel", "scipy"]


def _modules_after(code: str, lean: bool = True) -> dict[str, bool]:
    """Which of ``HEAVY`` a fresh ``python -c`` of ``code`` loaded: as a process MISS
    started (``lean``) or as a user's program."""
    probe = f"import sys\n{code}\nimport json\nprint(json.dumps({{m: m in sys.modules for m in {HEAVY!r}}}))"
    env = {k: v for k, v in os.environ.items() if k != "MISS_LEAN_IMPORT"}
    if lean:
        env["MISS_LEAN_IMPORT"] = "1"
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True, env=env
    )
    return json.loads(out.stdout)


def test_import_miss_in_a_process_miss_started_loads_no_heavy_library() -> None:
    assert _modules_after("import miss") == dict.fromkeys(HEAVY, False)


def test_import_miss_in_a_program_loads_what_the_api_calls_use() -> None:
    """VTK's filters and meshoptimizer (the surface, the simplifier, the GLB), not numba,
    the DICOM reader, SimpleITK, nibabel or scipy (a few calls need them: first use)."""
    loaded = _modules_after("import miss", lean=False)
    assert loaded == dict.fromkeys(HEAVY, False) | {"meshoptimizer": True}
    assert _modules_after("import miss, sys; assert 'vtkmodules' in sys.modules", lean=False)


def test_the_cli_parser_loads_no_heavy_library() -> None:
    loaded = _modules_after("from miss.cli import build_parser; build_parser()")
    assert loaded == dict.fromkeys(HEAVY, False)


def test_colour_tables_load_without_the_scene_builder() -> None:
    """The confined reader of a label-map upload (a process MISS starts) reads its colour
    table only."""
    assert _modules_after("import miss.structures.labels") == dict.fromkeys(HEAVY, False)


def test_documented_names_are_the_functions_after_their_modules_load() -> None:
    import miss
    import miss.decimate.quadric
    import miss.export.gltf
    import miss.structures.build  # noqa: F401

    assert callable(miss.decimate) and miss.decimate.__name__ == "decimate"
    assert callable(miss.export) and miss.export.__name__ == "export"
    assert miss.extract_scene.__module__ == "miss.structures.build"
    assert miss.Volume.__module__ == "miss.types"


def _run(*args: str, check: bool = True) -> tuple[int, set[str], list[str]]:
    """A ``python -X importtime -m miss.cli ARGS`` process: its exit code, every module it
    imported, and the rest of what it wrote on stderr."""
    proc = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "miss.cli", *args],
        capture_output=True, text=True, check=check, timeout=600,
    )  # fmt: skip
    lines = proc.stderr.splitlines()
    timed = [line for line in lines if line.startswith("import time:")]
    said = [line for line in lines if not line.startswith("import time:")]
    return proc.returncode, {line.rsplit("|", 1)[-1].strip() for line in timed[1:]}, said


def _imported_by(*args: str) -> set[str]:
    """Every module a ``python -m miss.cli ARGS`` process imported (``-X importtime``)."""
    return _run(*args)[1]


def test_a_path_that_is_not_there_is_said_before_the_job_loads() -> None:
    """A mistyped path is answered at once: before numpy, VTK or the job's code load (the
    command loads what its subcommand needs, not what ``import miss`` loads for the API)."""
    code, loaded, said = _run(
        "convert", "/no/such/scan", "--level", "300", "-o", "x.glb", check=False
    )
    assert code == 2
    assert not loaded & {"numpy", "vtkmodules", "miss.pipeline"}, sorted(loaded)
    assert said == ["miss: /no/such/scan: no such file or folder; check the path."]


def test_miss_help_loads_not_even_numpy() -> None:
    """``miss --help`` answers before numpy (a tenth of a second) would have loaded."""
    assert not _imported_by("--help") & {"numpy", *HEAVY}


def test_miss_help_loads_no_command_and_no_job_declaration() -> None:
    """``miss --help`` lists the commands from their one-line helps: no command's module,
    no job declaration (``miss.spec``, which ``convert``'s options are made from), no
    thread pool (the decimation's, loaded only when a check runs)."""
    loaded = _imported_by("--help")
    assert not loaded & {"miss.spec", "miss.cli.convert", "miss.cli.options", "concurrent.futures"}


def test_each_command_still_has_its_whole_help() -> None:
    """A command's own ``--help`` is built with its options (only that command's)."""
    # UTF-8 whatever the locale: the help has "mm³", and CI's locale is ASCII
    proc = subprocess.run(
        [sys.executable, "-m", "miss.cli", "convert", "--help"],
        capture_output=True, encoding="utf-8", timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0 and "--error-bound" in proc.stdout and "--level" in proc.stdout
    proc = subprocess.run(
        [sys.executable, "-m", "miss.cli", "user", "add", "--help"],
        capture_output=True, encoding="utf-8", timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0 and "--pacs" in proc.stdout


def test_help_on_an_ascii_terminal_does_not_crash() -> None:
    """A locale that cannot spell "mm³" (ASCII, Python's UTF-8 coercion off): the help is
    still printed, that character escaped."""
    import os

    env = {**os.environ, "LC_ALL": "C", "LANG": "C", "PYTHONCOERCECLOCALE": "0", "PYTHONUTF8": "0"}
    proc = subprocess.run(
        [sys.executable, "-m", "miss.cli", "convert", "--help"],
        capture_output=True, timeout=600, env=env,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr.decode("utf-8", "replace")
    assert b"--error-bound" in proc.stdout and b"mm\\xb3" in proc.stdout


@pytest.mark.parametrize(
    ("words", "hint"),
    [
        (["nope"], "(see 'miss --help')"),
        (["convert"], "(see 'miss convert --help')"),
        (["user", "add"], "(see 'miss user add --help')"),
    ],
)
def test_a_usage_error_names_the_help_of_the_command_typed(words: list[str], hint: str) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "miss.cli", *words], capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1
    assert proc.stderr.startswith("miss: ") and proc.stderr.rstrip().endswith(hint)


def test_python_dash_m_miss_is_the_command() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "miss", "--help"], capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0 and "convert" in proc.stdout


def _tiny_nrrd(path: Path) -> Path:
    """A 4 x 4 x 4 label map (0 and 1) as an attached NRRD."""
    header = b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 4 4 4\nencoding: raw\n\n"
    path.write_bytes(header + bytes(32) + bytes([1]) * 32)
    return path


def _tiny_nifti(path: Path) -> Path:
    """The same label map as a plain .nii.gz (an sform, no scaling, no extensions)."""
    import nibabel as nib
    import numpy as np

    labels = np.zeros((4, 4, 4), dtype=np.uint8)
    labels[:, :, 2:] = 1
    nib.save(nib.Nifti1Image(labels, np.eye(4)), path)
    return path


@pytest.mark.parametrize("kind", ["nrrd", "nifti", "CT"])
def test_miss_info_loads_only_the_reader_it_needs(
    kind: str, tmp_path: Path, demo_file: Path
) -> None:
    """``miss info`` reads and counts labels with numpy: no surface library, no other
    format's reader, and for a plain NIfTI file not even nibabel (which loads pydicom)."""
    make = {"nrrd": _tiny_nrrd, "nifti": _tiny_nifti, "CT": lambda p: demo_file}[kind]
    path = make(tmp_path / ("labels.nrrd" if kind == "nrrd" else "labels.nii.gz"))
    assert not _imported_by("info", str(path)) & {"vtkmodules", "scipy", *HEAVY}
