"""The command line as a user runs it: real processes, exit codes, one-line errors."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest


def miss(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run(
        [sys.executable, "-m", "miss.cli", *args], capture_output=True, text=True, timeout=600
    )
    if check:
        assert proc.returncode == 0, proc.stderr
    return proc


def test_info_json_describes_the_volume(demo_file: Path) -> None:
    info = json.loads(miss("info", str(demo_file), "--json").stdout)
    assert info["dims"] == [128, 128, 128]
    assert info["spacing"] == pytest.approx([1.5, 1.5, 1.5])
    assert len(info["affine"]) == 4 and info["affine"][0][0] == pytest.approx(
        1.5
    )  # LPS, x to the left
    assert info["range"][0] <= -900 and info["range"][1] >= 1000
    assert set(info) >= {"dims", "spacing", "affine", "dtype", "range", "modality", "series"}


def test_convert_writes_every_output_and_reports_json(demo_file: Path, tmp_path: Path) -> None:
    outs = [tmp_path / f"bone.{ext}" for ext in ("wrl", "wrz", "glb", "stl")]
    args = ["convert", str(demo_file), "--level", "300", "--sample-rate", "2", "--json"]
    args += ["--measure", "--schedule", "paper"]
    for out in outs:
        args += ["-o", str(out)]
    stats = json.loads(miss(*args).stdout)
    assert [o["path"] for o in stats["outputs"]] == [str(o) for o in outs]
    for out, entry in zip(outs, stats["outputs"], strict=True):
        assert out.stat().st_size == entry["bytes"] > 0
    assert outs[0].read_bytes().startswith(b"#VRML V2.0 utf8")
    assert set(stats["seconds"]) >= {"read", "surface", "decimate", "write", "total"}
    dec = stats["decimation"]
    assert dec["method"] == "quadric" and dec["max_error_mm"] > 0 and dec["mean_error_mm"] > 0
    assert stats["triangles"] < 0.15 * dec["triangles_before"]


def test_start_and_end_slice_cut_the_model(demo_file: Path, tmp_path: Path) -> None:
    base = ["convert", str(demo_file), "--level", "300", "--decimate", "none", "--json"]
    full = json.loads(miss(*base, "-o", str(tmp_path / "a.stl")).stdout)
    half = json.loads(
        miss(
            *base, "--start-slice", "64", "--end-slice", "128", "-o", str(tmp_path / "b.stl")
        ).stdout
    )
    assert 0.3 * full["triangles"] < half["triangles"] < 0.8 * full["triangles"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["info", "/no/such/scan"], "no such file"),
        (["convert", "/no/such/scan", "--level", "300", "-o", "{tmp}/x.stl"], "no such file"),
        (
            ["convert", "{demo}", "--label-map", "/no/such.nii", "-o", "{tmp}/x.stl"],
            "/no/such.nii: no such file or folder; check the path.",
        ),
        (["convert", "{demo}", "--level", "300", "-o", "{tmp}/x.dxf"], "unknown output extension"),
        (["convert", "{demo}", "--level", "99999", "-o", "{tmp}/x.stl"], "no surface at level"),
        (
            [
                "convert",
                "{demo}",
                "--level",
                "300",
                "--start-slice",
                "100",
                "--end-slice",
                "400",
                "-o",
                "{tmp}/x.stl",
            ],
            "outside 1..128",
        ),
        (["convert", "{demo}", "--level", "300", "--reduce", "1.5", "-o", "{tmp}/x.stl"], "reduce"),
        (["convert", "{truncated}", "--level", "300", "-o", "{tmp}/x.stl"], "truncated.nii.gz"),
        (["convert", "{demo}", "-o", "{tmp}/x.stl"], "--level"),
    ],
)
def test_bad_input_gives_one_line_and_exit_2(
    demo_file: Path, tmp_path: Path, args: list[str], message: str
) -> None:
    truncated = tmp_path / "truncated.nii.gz"
    truncated.write_bytes(demo_file.read_bytes()[:5000])
    subs = {"{demo}": str(demo_file), "{tmp}": str(tmp_path), "{truncated}": str(truncated)}
    for key, value in subs.items():
        args = [a.replace(key, value) for a in args]
    proc = miss(*args, check=False)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert message in lines[0]
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "x.stl").exists()


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (["--bogus"], "unknown option --bogus (see 'miss --help')"),
        (
            ["convert", "/no/such/scan", "--level", "300", "-o", "x.stl", "--bogus"],
            "unknown option --bogus (see 'miss convert --help')",
        ),
        (["convert", "--bogus"], "unknown option --bogus (see 'miss convert --help')"),
        (
            ["serve", "--prot", "1"],
            "unknown option --prot (did you mean --port?) (see 'miss serve --help')",
        ),
        (["user", "add", "--bogus=1"], "unknown option --bogus (see 'miss user add --help')"),
        (["pacs", "--bogus"], "unknown option --bogus (see 'miss pacs --help')"),
    ],
)
def test_an_unknown_option_is_named_first_with_the_help_of_its_command(
    args: list[str], line: str
) -> None:
    """Not "arguments are required", nor a hint at ``miss --help`` for a command's option."""
    proc = miss(*args, check=False)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr == f"miss: {line}\n"


def test_a_negative_level_is_a_number_not_an_unknown_option(tmp_path: Path) -> None:
    proc = miss("convert", "/no/such/scan", "--level", "-500", "-o", str(tmp_path / "x.stl"),
                check=False)  # fmt: skip
    assert proc.returncode == 2 and "no such file" in proc.stderr
    assert "unknown option" not in proc.stderr


def test_cthead_bone_gives_about_545k_triangles(datasets: Path, tmp_path: Path) -> None:
    out = tmp_path / "cthead.stl"
    stats = json.loads(
        miss(
            "convert",
            str(datasets / "ct_head_stanford_cthead" / "CThead.nhdr"),
            "--level",
            "1500",
            "--decimate",
            "none",
            "--json",
            "-o",
            str(out),
        ).stdout
    )
    assert stats["triangles"] == pytest.approx(545_000, rel=0.03)


@pytest.mark.slow
def test_json_keeps_its_keys(demo_file: Path, tmp_path: Path) -> None:
    """``--json`` still says everything it said: scripts read these names."""
    args = ["convert", str(demo_file), "--level", "300", "--sample-rate", "3", "--json"]
    stats = json.loads(miss(*args, "-o", str(tmp_path / "b.glb")).stdout)
    assert set(stats) >= {
        "triangles", "vertices", "seconds", "decimation", "parts", "notes", "outputs",
    }  # fmt: skip
    assert set(stats["seconds"]) >= {"read", "surface", "decimate", "write", "total"}
    assert set(stats["decimation"]) >= {
        "method", "reduce", "error_bound", "triangles_before", "achieved_reduction",
        "max_error_mm", "mean_error_mm",
    }  # fmt: skip
    (part,) = stats["parts"]
    assert set(part) >= {
        "name", "label", "color", "opacity", "triangles", "vertices", "volume_ml", "area_cm2",
    }  # fmt: skip
    assert [set(o) for o in stats["outputs"]] == [{"path", "bytes"}]
    # The default schedule holds its bound, so it always measures; the paper's measures
    # when asked (about a second: numba loads); the keys are there either way.
    decimation = stats["decimation"]
    assert decimation["bound_held"] and decimation["max_error_mm"] <= decimation["bound_mm"]
    assert decimation["stopped_by"] in ("bound", "reduce")
    # quadric asked for, the held model schroeder's: the report names the one that made it
    assert decimation["finished_with"] == "schroeder"
    paper = [*args, "--schedule", "paper", "-o", str(tmp_path / "p.glb")]
    unmeasured = json.loads(miss(*paper).stdout)["decimation"]
    assert unmeasured["max_error_mm"] is None and unmeasured["finished_with"] == "quadric"
    text = miss(*args[:-1], "--schedule", "paper", "-o", str(tmp_path / "c.glb")).stdout
    assert "before quadric decimation; error not measured: add --measure" in text
    held = miss(*args[:-1], "-o", str(tmp_path / "d.glb")).stdout
    assert "before schroeder decimation; max error" in held


def _convert_stderr(demo_file: Path, out: Path, terminal: bool) -> str:
    """What ``miss convert`` writes on stderr when stderr is a terminal, or a pipe."""
    import pty

    args = [sys.executable, "-m", "miss", "convert", str(demo_file), "--level", "300",
            "--sample-rate", "3", "-o", str(out)]  # fmt: skip
    if not terminal:
        return subprocess.run(args, capture_output=True, text=True, timeout=600, check=True).stderr
    leader, follower = pty.openpty()
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=follower)
    os.close(follower)
    chunks = []
    while True:
        try:
            chunk = os.read(leader, 4096)
        except OSError:  # the follower side closed: the process is done writing
            break
        if not chunk:
            break
        chunks.append(chunk)
    os.close(leader)
    assert proc.wait(timeout=600) == 0
    return b"".join(chunks).decode()


def test_progress_bar_on_a_terminal_and_nothing_on_a_pipe(demo_file: Path, tmp_path: Path) -> None:
    drawn = _convert_stderr(demo_file, tmp_path / "a.stl", terminal=True)
    assert "[" + "#" * 30 + "] 100%" in drawn and "surface" in drawn
    assert _convert_stderr(demo_file, tmp_path / "b.stl", terminal=False) == ""
