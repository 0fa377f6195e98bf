"""Time and peak memory of MISS's job against the number of voxels, 128^3 to 512 x 512 x 1000.

    .venv/bin/python benchmarks/scaling.py [--repeats 3] [--largest 1000]

Each volume is the CThead resampled (trilinear, int16) to the given size and saved as
uncompressed NIfTI. For each size a fresh process warms up, then runs the web system's job
(``load_volume`` + ``pipeline.run``: surface, quadric decimation to 10 % with the deviation
measured, GLB and VRML) ``repeats`` times; the first run's peak resident memory above the
process's baseline is the peak, the median of the runs the time. The level is bone (1500).

Writes ``results/scaling.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from common import (
    CACHE,
    child_peak,
    markdown_table,
    peak_since,
    save,
    start_peak,
    warm_up_file,
    write_nifti,
)
from paper import default_cthead, resample_axis

import miss
from miss.pipeline import run
from miss.spec import JobSpec

LEVEL = 1500.0
SIZES: tuple[tuple[int, int, int], ...] = (
    (128, 128, 128),
    (256, 256, 113),
    (256, 256, 225),
    (256, 256, 450),
    (384, 384, 500),
    (512, 512, 500),
    (512, 512, 1000),
)


def volume_file(shape: tuple[int, int, int]) -> Path:
    """CThead resampled to ``shape`` as ``.nii`` in the cache (made once; z first, cheapest)."""
    path = CACHE / f"cthead_{shape[0]}x{shape[1]}x{shape[2]}.nii"
    if path.is_file():
        return path
    volume = miss.load_volume(default_cthead())
    for axis in (2, 0, 1):
        if volume.data.shape[axis] != shape[axis]:
            volume = resample_axis(volume, axis, shape[axis])
    return write_nifti(volume, path)


def _job(path: Path) -> dict[str, float]:
    t0 = time.perf_counter()
    volume = miss.load_volume(path)
    read = time.perf_counter() - t0
    result = run(volume, JobSpec.of(level=LEVEL, formats=("glb", "wrl")))
    seconds = {"read": read, **result.seconds, "measure": result.report.measure_seconds}
    seconds["total"] = time.perf_counter() - t0
    seconds["triangles_in"] = result.report.triangles_in
    seconds["triangles_out"] = result.mesh.n_triangles
    seconds["output_bytes"] = sum(len(a) for a in result.artifacts.values())
    seconds["voxel_bytes"] = volume.data.nbytes
    return seconds


def child(args: list[str]) -> None:
    """One size in a fresh process: warm up, a measured first run, then timed repeats."""
    path, repeats = Path(args[0]), int(args[1])
    run(miss.load_volume(warm_up_file()), JobSpec.of(level=300.0, formats=("glb", "wrl")))
    baseline = start_peak()
    runs = [_job(path)]
    peak = peak_since(baseline)
    runs += [_job(path) for _ in range(repeats - 1)]
    med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    print(json.dumps({"peak_bytes": peak, "median": med, "totals": [r["total"] for r in runs]}))


def report(rows: list[dict[str, Any]]) -> str:
    table = []
    for r in rows:
        m, mvox = r["median"], r["voxels"] / 1e6
        budget = 3 * m["voxel_bytes"] + m["output_bytes"]
        table.append(
            [
                "x".join(map(str, r["shape"])),
                round(mvox, 1),
                m["read"],
                m["surface"],
                m["decimate"],
                m["measure"],
                m["write"],
                m["total"],
                1000 * m["total"] / mvox,
                int(m["triangles_in"]),
                r["peak_bytes"] / 2**20,
                r["peak_bytes"] / m["voxel_bytes"],
                "yes" if r["peak_bytes"] <= budget else "no",
            ]
        )
    slope = _slope(rows)
    return (
        markdown_table(
            [
                "voxels",
                "Mvoxel",
                "read s",
                "surface s",
                "decimate s",
                "measure s",
                "write s",
                "total s",
                "ms / Mvoxel",
                "triangles",
                "peak MB",
                "peak / volume bytes",
                "<= 3x volume + output",
            ],
            table,
        )
        + f"\nlog-log slope of total time against voxels: {slope:.2f} (1.00 = linear)\n"
    )


def _slope(rows: list[dict[str, Any]]) -> float:
    x = np.log([r["voxels"] for r in rows])
    y = np.log([r["median"]["total"] for r in rows])
    return float(np.polyfit(x, y, 1)[0]) if len(rows) > 1 else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--largest", type=int, default=1000, help="skip sizes with more slices")
    args = parser.parse_args()
    rows = []
    for shape in SIZES:
        if shape[2] > args.largest:
            continue
        res = child_peak(Path(__file__), [str(volume_file(shape)), str(args.repeats)], timeout=1500)
        rows.append({"shape": shape, "voxels": int(np.prod(shape)), **res})
        print(
            f"{shape}: {res['median']['total']:.2f} s, peak {res['peak_bytes'] / 2**20:.0f} MB",
            file=sys.stderr,
            flush=True,
        )
    table = report(rows)
    save("scaling", {"level": LEVEL, "repeats": args.repeats, "rows": rows}, table)
    print(table)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(sys.argv[2:])
    else:
        main()
