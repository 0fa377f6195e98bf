"""MISS's bounded methods (placed and half-edge collapse, schroeder) against the unbounded
quadric: triangles and time, and where placed's time goes.

    .venv/bin/python benchmarks/collapse.py [--cases a,b] [--runs 3] [--out DIR]
                                            [--dense-samples N]

For each surface and bound (a fraction of the bounding-box diagonal), MISS's three bounded
methods run as a job runs them (``decimate(..., reduce=0.99)``, the guaranteed schedule:
the bound decides where they stop, and the run is checked, :func:`miss.measure.bound_check`),
and MISS's unbounded quadric as before bounds were held (to 10 %, nothing checked). Each is
timed ``--runs`` times (the median reported): the whole call, and within it the
decimation's and the check's seconds from the report. Each bounded output is also measured
densely here (:func:`miss.measure._jit.between`, seed 5), not by the method. Placed's
kernel is run once more on its own for its counts (vertices tried, overlays weighed,
collapses by where the vertex went) and its time per collapse. Writes
``results/collapse.{json,md}``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from common import case_surfaces, warm_methods, write_result
from paper import machine

import miss
from miss.decimate.placed import COUNTS, placed
from miss.measure._jit import between
from miss.types import Mesh

RESULTS = Path(__file__).resolve().parent / "results"
REDUCE = 0.99
DATASETS = Path(
    os.environ.get("MISS_DATASETS", Path(__file__).resolve().parents[2] / "shared" / "datasets")
)


def cases(root: Path = DATASETS) -> dict[str, tuple[Path, float, tuple[float, ...]]]:
    """Surface name -> (volume, level in the volume's units, bounds)."""
    cthead = root / "ct_head_stanford_cthead" / "CThead.nhdr"
    return {
        "CThead bone": (cthead, 1500.0, (0.002, 0.0005)),
        "CThead skin": (cthead, 600.0, (0.002, 0.0005)),
        "MR DICOM head skin": (root / "mr_head_dicom_vsseg001_t1", 270.0, (0.002, 0.0002)),
    }


def _median_run(mesh: Mesh, method: str, bound: float, runs: int) -> dict[str, Any]:
    """Median seconds of ``runs`` bounded runs (whole call, decimation, check), the last
    run's output and report."""
    walls, cpus, decimating, checking = [], [], [], []
    for _ in range(runs):
        start, cpu = time.perf_counter(), time.process_time()
        out, report = miss.decimate(mesh, method, REDUCE, bound)
        walls.append(time.perf_counter() - start)
        cpus.append(time.process_time() - cpu)
        decimating.append(report.seconds)
        checking.append(report.measure_seconds)
    return {
        "out": out,
        "report": report,
        "seconds": statistics.median(walls),
        "cpu_seconds": statistics.median(cpus),
        "decimate_seconds": statistics.median(decimating),
        "check_seconds": statistics.median(checking),
    }


def unbounded(mesh: Mesh, runs: int) -> tuple[int, float, float]:
    """MISS's quadric as before bounds were held (to 10 %, unchecked): (triangles, median
    wall s, median CPU s)."""
    walls, cpus, out = [], [], mesh
    for _ in range(runs):
        start, cpu = time.perf_counter(), time.process_time()
        out = miss.decimate(mesh, "quadric", 0.9, 0.0002, schedule="paper", measure=False)[0]
        walls.append(time.perf_counter() - start)
        cpus.append(time.process_time() - cpu)
    return out.n_triangles, statistics.median(walls), statistics.median(cpus)


def bench_case(
    mesh: Mesh, bounds: tuple[float, ...], runs: int, samples: int, log: Any
) -> dict[str, Any]:
    """Rows per bound for one surface."""
    triangles, reference, reference_cpu = unbounded(mesh, runs)
    case: dict[str, Any] = {"triangles_in": mesh.n_triangles, "diagonal_mm": mesh.diagonal(),
                            "quadric_triangles": triangles, "quadric_seconds": reference,
                            "quadric_cpu_seconds": reference_cpu,
                            "bounds": {}}  # fmt: skip
    for bound in bounds:
        rows = []
        for method in ("placed", "collapse", "schroeder"):
            run = _median_run(mesh, method, bound, runs)
            report = run.pop("report")
            out = run.pop("out")
            dense = between(mesh, out, samples, seed=5)
            rows.append({"method": method, "triangles": out.n_triangles, **run,
                         "max_mm": report.max_error_mm, "dense_max_mm": dense,
                         "bound_mm": report.bound_mm, "rounds": report.rounds,
                         "holds_densely": dense <= report.bound_mm + 1e-6 * mesh.diagonal(),
                         "over_quadric": run["seconds"] / reference})  # fmt: skip
            log(f"  {bound} {method}: {out.n_triangles} triangles, {run['seconds']:.2f} s")
        case["bounds"][str(bound)] = rows
        counts = np.zeros(len(COUNTS), np.int64)
        start = time.perf_counter()
        placed(mesh, REDUCE, bound * mesh.diagonal(), counts=counts)
        seconds = time.perf_counter() - start
        case.setdefault("placed_counts", {})[str(bound)] = {
            "seconds": seconds,
            **dict(zip(COUNTS, counts.tolist(), strict=True)),
        }
    return case


def markdown(result: dict[str, Any]) -> str:
    lines = [
        "| surface | triangles in | bound | method | triangles | vs schroeder | seconds "
        "(decimate + check) | x unbounded quadric | CPU s | CPU x quadric | max mm (check) | dense max mm | bound mm "
        "| holds densely |\n",
        "| --- | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: "
        "| --- |\n",
    ]
    for name, case in result["cases"].items():
        lines.append(
            f"| {name} | {case['triangles_in']} | - | quadric, unbounded (to 10 %) "
            f"| {case['quadric_triangles']} | | {case['quadric_seconds']:.3f} | 1.0 "
            f"| {case['quadric_cpu_seconds']:.3f} | 1.0 | | | | |\n"
        )
        for bound, rows in case["bounds"].items():
            schroeder = next(r for r in rows if r["method"] == "schroeder")["triangles"]
            for r in rows:
                lines.append(
                    f"| {name} | {case['triangles_in']} | {bound} | {r['method']} "
                    f"| {r['triangles']} | {r['triangles'] / schroeder - 1:+.1%} "
                    f"| {r['seconds']:.3f} ({r['decimate_seconds']:.3f} + "
                    f"{r['check_seconds']:.3f}) | {r['over_quadric']:.1f} | {r['cpu_seconds']:.3f} "
                    f"| {r['cpu_seconds'] / case['quadric_cpu_seconds']:.1f} | {r['max_mm']:.4f} "
                    f"| {r['dense_max_mm']:.4f} | {r['bound_mm']:.4f} "
                    f"| {'yes' if r['holds_densely'] else 'no'} |\n"
                )
    lines += [
        "\nWhere placed's time goes (its kernel alone, once; collapses = the last three "
        "columns):\n\n| surface | bound | seconds | "
        + " | ".join(COUNTS)
        + " | µs per collapse | overlays per collapse |\n",
        "| --- | ---: | ---: | " + " | ".join("---:" for _ in COUNTS) + " | ---: | ---: |\n",
    ]
    for name, case in result["cases"].items():
        for bound, c in case.get("placed_counts", {}).items():
            done = max(sum(c[k] for k in COUNTS[3:]), 1)
            lines.append(
                f"| {name} | {bound} | {c['seconds']:.2f} | "
                + " | ".join(str(c[k]) for k in COUNTS)
                + f" | {1e6 * c['seconds'] / done:.1f} | {c[COUNTS[2]] / done:.1f} |\n"
            )
    return "".join(lines)


def run(out: Path, names: list[str] | None, runs: int, samples: int, log: Any) -> dict[str, Any]:
    """Measure every case (all by default), write ``collapse.{json,md}`` into ``out``."""
    chosen = {k: v for k, v in cases().items() if names is None or k in names}
    warm_methods(("quadric", "schroeder", "collapse", "placed"))
    result: dict[str, Any] = {"machine": machine(), "reduce": REDUCE, "runs": runs, "cases": {}}
    for name, mesh, (bounds,) in case_surfaces(chosen, log, normals=False):
        result["cases"][name] = bench_case(mesh, bounds, runs, samples, log)
    write_result(out, "collapse", result, markdown(result))
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", default=None, help="comma-separated names (default: all)")
    parser.add_argument("--runs", type=int, default=3, help="timed runs per row (median)")
    parser.add_argument("--dense-samples", type=int, default=200_000, metavar="N")
    parser.add_argument("--out", default=str(RESULTS), help="folder for JSON and Markdown")
    args = parser.parse_args(argv)
    names = args.cases.split(",") if args.cases else None
    unknown = set(names or ()) - set(cases())
    if unknown:
        print(f"unknown case(s) {sorted(unknown)}; choose from {sorted(cases())}", file=sys.stderr)
        return 2
    log = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
    result = run(Path(args.out), names, args.runs, args.dense_samples, log)
    print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
