"""What the benchmark scripts share: the paper's volume as a file, timing, peak memory, tables.

Timing: wall-clock medians over repeats, the candidates of one comparison run round-robin
inside each repeat so that the noise of a shared machine falls on all of them alike.

Peak memory: each measurement runs in a fresh Python process that imports everything and
warms up on a small input, then resets the kernel's high-water mark (``/proc/self/clear_refs``
5) and records ``VmRSS``; the job's peak is ``VmHWM`` afterwards minus that baseline. This
counts every allocation, numpy's, VTK's C++ and numba's alike, and nothing of earlier runs.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from paper import machine, paper_volume

from miss.demo import phantom
from miss.types import Volume

RESULTS = Path(__file__).resolve().parent / "results"
CACHE = Path(os.environ.get("MISS_BENCH_CACHE", Path(tempfile.gettempdir()) / "miss-bench"))


def write_nifti(volume: Volume, path: Path) -> Path:
    """Save ``volume`` as uncompressed NIfTI (RAS affine), the file every job reads."""
    import nibabel as nib

    ras = np.diag([-1.0, -1.0, 1.0, 1.0]) @ volume.affine
    image = nib.Nifti1Image(np.asarray(volume.data), ras)
    image.header.set_xyzt_units("mm")
    path.parent.mkdir(parents=True, exist_ok=True)
    nib.save(image, str(path))
    return path


def warm_up_file() -> Path:
    """A small volume (64 x 64 x 1920, 16 MB) that still takes every path a big one takes:
    surface slabs with seams, the two-phase parallel quadric, the numba kernels. A child
    runs its job on it first, so that JIT compilation and first-use allocations of those
    paths are not counted as the job's memory or time."""
    path = CACHE / "warm_64x64x1920.nii"
    if not path.is_file():
        tile = phantom(64, spacing=4.0)
        write_nifti(Volume(np.tile(tile.data, (1, 1, 30)), tile.affine), path)
    return path


def paper_volume_file() -> Path:
    """CThead at 256 x 256 x 225 as ``.nii`` in the cache folder (made once)."""
    path = CACHE / "cthead_256x256x225.nii"
    if not path.is_file():
        write_nifti(paper_volume(), path)
    return path


def round_robin(
    candidates: dict[str, Callable[[], Any]],
    repeats: int,
    cpu: dict[str, list[float]] | None = None,
) -> tuple[dict[str, list[float]], dict[str, Any]]:
    """Run every candidate once per repeat, in turn; seconds per run and each one's last result.

    ``cpu``, when given, receives the process CPU seconds of each run (all threads): beside
    the wall time it tells how much of a job's speed came from a second core.
    """
    seconds: dict[str, list[float]] = {name: [] for name in candidates}
    last: dict[str, Any] = {}
    for _ in range(repeats):
        for name, fn in candidates.items():
            t0, c0 = time.perf_counter(), time.process_time()
            last[name] = fn()
            seconds[name].append(time.perf_counter() - t0)
            if cpu is not None:
                cpu.setdefault(name, []).append(time.process_time() - c0)
    return seconds, last


def median(values: Sequence[float]) -> float:
    return float(statistics.median(values))


def _status(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(f"{field} not in /proc/self/status")


def resident_peak() -> int:
    """Bytes of this process's highest resident set so far (``VmHWM``)."""
    return _status("VmHWM")


def start_peak() -> int:
    """Reset the high-water mark; returns the resident bytes now (the baseline)."""
    Path("/proc/self/clear_refs").write_text("5")
    return _status("VmRSS")


def peak_since(baseline: int) -> int:
    """Bytes of the highest resident set since :func:`start_peak`, above its baseline."""
    return _status("VmHWM") - baseline


def child_peak(script: Path, args: Sequence[str], timeout: float = 300.0) -> dict[str, Any]:
    """Run ``script --child ARGS`` in a fresh interpreter; it prints one JSON line last."""
    proc = subprocess.run(
        [sys.executable, str(script), "--child", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"{script.name} --child {' '.join(args)} failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A Markdown table; numbers right-aligned."""
    align = [
        "---:" if rows and isinstance(rows[0][i], int | float) else "---"
        for i in range(len(header))
    ]
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join(align) + " |"]
    lines += ["| " + " | ".join(_cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def _cell(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.3f}" if abs(value) < 100 else f"{value:.0f}"
    return str(value)


def save(name: str, data: dict[str, Any], table: str, folder: Path = RESULTS) -> None:
    """``results/NAME.json`` (with the machine) and ``results/NAME.md`` (or in ``folder``)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{name}.json").write_text(json.dumps({"machine": machine(), **data}, indent=1))
    (folder / f"{name}.md").write_text(table)


def tree_rss(
    proc: subprocess.Popen, seen: Callable[[Any, float], None] | None = None, poll: float = 0.02
) -> float:
    """Poll ``proc``'s process tree until it ends; the highest sum of its resident memory
    (MB). ``seen(process, mb)`` is told each process's RSS at each poll."""
    import psutil

    root, peak = psutil.Process(proc.pid), 0.0
    while proc.poll() is None:
        now = 0.0
        try:
            tree = [root, *root.children(recursive=True)]
        except psutil.NoSuchProcess:
            break
        for p in tree:
            try:
                rss = p.memory_info().rss / 2**20
                if seen is not None:
                    seen(p, rss)
            except psutil.NoSuchProcess:
                continue
            now += rss
        peak = max(peak, now)
        time.sleep(poll)
    return peak


def warm_methods(methods: Sequence[str]) -> None:
    """Decimate a small phantom's surface with each method: numba's kernels loaded (or
    compiled) before anything is timed."""
    import miss

    warm = miss.extract_surface(phantom(48, spacing=4.0), 200.0)
    for method in methods:
        miss.decimate(warm, method, 0.9, 0.001)


def case_surfaces(
    chosen: dict[str, tuple[Any, ...]], log: Callable[[str], None], **options: Any
) -> Iterator[tuple[str, Any, tuple[Any, ...]]]:
    """For each case ``name: (path, level, *rest)``: its name, its surface at ``level``
    (``extract_surface`` with ``options``) and ``rest``; each volume read once."""
    import miss

    volumes: dict[Path, Volume] = {}
    for name, (path, level, *rest) in chosen.items():
        if path not in volumes:
            volumes[path] = miss.load_volume(path)
        log(name)
        yield name, miss.extract_surface(volumes[path], level, **options), tuple(rest)


def write_result(out: Path, stem: str, result: dict[str, Any], text: str) -> None:
    """``result`` as ``out/stem.json`` and ``text`` as ``out/stem.md``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.json").write_text(json.dumps(result, indent=1))
    (out / f"{stem}.md").write_text(text)
