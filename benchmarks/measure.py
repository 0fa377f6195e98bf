"""What measuring a decimation's error costs, beside the job it measures.

    .venv/bin/python benchmarks/measure.py [--repeats 5] [--fresh-repeats 5] [--before REF] [--out DIR]

The job is the public API's: ``load_volume`` -> ``extract_surface`` (or ``extract_scene``
for a label map) -> quadric decimation to 10 % -> GLB and VRML, with ``measure=False``. The
measurement is :func:`miss.measure._jit.deviation` on what the job made: 100 000 samples a side
for a surface, ``MEASURE_SAMPLES`` a part for a label map's scene, as the job itself would
measure. "Old" is the implementation at ``--before`` (default: before issue 14; ``git show
REF:src/miss/deviation.py`` loaded as a module of its own), run in the same session,
alternately with the new one.

- **warm**: one process; the job, the new measurement and the old one round-robin
  ``--repeats`` times (after one untimed round), medians.
- **fresh**: a new interpreter per run, new and old alternately, ``--fresh-repeats`` each: the
  job with every import it needs, then the measurement with every import *it* still needs
  (the old module's kernels, loaded from numba's cache) and its first calls. The job's peak
  is the process's ``VmHWM``; the measurement's is its high-water mark above the job's
  resident set (the mark is reset between them).

Share = measurement / (job + measurement): the part of a measured job spent measuring.

**The default job** (a second table, for the threshold cases): what a user's job does when
they change nothing, ``decimate`` under the ``guaranteed`` schedule (quadric to 10 % within
0.002 of the diagonal), whose check (``miss.measure._jit.bound_check``: every dropped input
vertex, every new edge's and triangle's middle) is the measurement and holds the bound: a
round out of bound is repeated with the regions locked. Its share is the report's
``measure_seconds`` (all rounds' checks) over the whole job's time, that included, warm
(medians of ``--repeats`` in one process) and fresh (a new interpreter per run, imports
counted in the job).

**The measuring job as MISS runs it** (a third table): the first table's job (quadric to
10 %, the paper's schedule, GLB and VRML), measured and not; the share is the time
measuring adds to the whole job: (measured - unmeasured) / measured. Warm (numba loaded,
as in a server's worker): :func:`miss.pipeline.run`, round-robin in one process, medians;
the measurement's half that needs only the undecimated surface is made while the job
decimates (:func:`miss.decimate.measuring_later`), the rest while the files after the GLB
are written. Fresh: ``miss convert`` as a user runs it (its ``main`` in a new interpreter
each, alternately, the whole process timed from outside, its imports and start
included); a measured one starts its measuring process first thing
(:mod:`miss.measure.measurer`). "same figures": the fresh runs' max and mean are the warm ones.

Writes ``results/measure.{json,md}``.
"""

from __future__ import annotations

import time

START = time.perf_counter()  # a fresh child's clock starts before its first import

import argparse  # noqa: E402
import importlib.util  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
from collections.abc import Callable, Iterator  # noqa: E402
from functools import partial  # noqa: E402
from pathlib import Path  # noqa: E402
from types import ModuleType  # noqa: E402
from typing import Any  # noqa: E402

HERE = Path(__file__).resolve().parent
#: The commit whose deviation.py is "old": main before issue 14.
BEFORE = "5984b47"
REDUCE = 0.9


def datasets() -> Path:
    """``../shared/datasets`` beside the repository, or ``$MISS_DATASETS`` (a worktree's)."""
    return Path(os.environ.get("MISS_DATASETS", HERE.parent.parent / "shared" / "datasets"))


def cases() -> dict[str, tuple[Path, dict[str, Any]]]:
    """Name -> (file, what to extract): levels in the file's units."""
    root = datasets()
    cthead = root / "ct_head_stanford_cthead" / "CThead.nhdr"
    return {
        "CThead bone": (cthead, {"level": 1500.0}),
        "CThead skin": (cthead, {"level": 600.0}),
        "MR headsq skin": (root / "mr_headsq_quarter" / "quarter.nhdr", {"level": 500.0}),
        "frog label map": (root / "labels_frogtissue" / "frogtissue.mhd", {"labels": "all"}),
    }


# ----------------------------------------------------------------------------- the job


Pair = tuple[Any, Any, int]  # (undecimated, decimated, samples)


def run_job(path: Path, what: dict[str, Any]) -> list[Pair]:
    """The job with ``measure=False``; returns what a measuring job would have compared."""
    import miss
    from miss.geometry import locality_order

    volume = miss.load_volume(path)
    if "level" in what:
        surface = miss.extract_surface(volume, what["level"])
        mesh, _ = miss.decimate(surface, "quadric", REDUCE, measure=False, schedule="paper")
        mesh = locality_order(mesh)  # laid out as a job lays out its scene (and measures it)
        miss.export(mesh, "glb")
        miss.export(mesh, "wrl")
        return [(surface, mesh, 100_000)]
    return _scene_pairs(volume, what["labels"])


def run_default(path: Path, what: dict[str, Any]) -> dict[str, Any]:
    """The default job (see the module's docstring): its seconds, its check's and figures."""
    import miss

    start = time.perf_counter()
    volume = miss.load_volume(path)
    surface = miss.extract_surface(volume, what["level"])
    mesh, report = miss.decimate(surface)
    miss.export(mesh, "glb")
    miss.export(mesh, "wrl")
    return {
        "job_seconds": time.perf_counter() - start,
        "measure_seconds": report.measure_seconds,
        "rounds": report.rounds,
        "finished_with": report.finished_with,
        "triangles": mesh.n_triangles,
        "max_mm": report.max_error_mm,
        "bound_mm": report.bound_mm,
    }


def run_pipeline(path: Path, what: dict[str, Any], measure: bool) -> dict[str, Any]:
    """The first table's job through :func:`miss.pipeline.run`, measured or not."""
    import miss
    from miss.pipeline import run
    from miss.spec import JobSpec

    start = time.perf_counter()
    volume = miss.load_volume(path)
    spec = JobSpec.of(
        level=what["level"], decimate="quadric", reduce=REDUCE, schedule="paper",
        formats=("glb", "wrl"),
    )  # fmt: skip
    result = run(volume, spec, measure=measure)
    return {
        "job_seconds": time.perf_counter() - start,
        "max_mm": result.report.max_error_mm,
        "mean_mm": result.report.mean_error_mm,
        "triangles": result.scene.n_triangles,
    }


def run_command(path: Path, what: dict[str, Any], measure: bool) -> dict[str, Any]:
    """The same job as a user runs it, ``miss convert`` (its ``main``, in this fresh
    interpreter): a measured one starts its measuring process first thing
    (:mod:`miss.measure.measurer`), as the command does."""
    import contextlib
    import io
    import tempfile

    from miss.cli import main

    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stdout(io.StringIO()) as out:
        words = [
            "convert", str(path), "--level", str(what["level"]), "--decimate", "quadric",
            "--reduce", str(REDUCE), "--schedule", "paper", "--json",
            "-o", f"{tmp}/m.glb", "-o", f"{tmp}/m.wrl", *(["--measure"] if measure else []),
        ]  # fmt: skip
        if main(words) != 0:
            raise RuntimeError(f"miss {' '.join(words)} failed")
    stats = json.loads(out.getvalue())
    return {
        "job_seconds": time.perf_counter() - start,
        "max_mm": stats["decimation"]["max_error_mm"],
        "mean_mm": stats["decimation"]["mean_error_mm"],
        "triangles": stats["triangles"],
    }


def threshold_cases(names: list[str]) -> Iterator[tuple[str, Path, dict[str, Any]]]:
    """(name, file, what to extract) of each case of ``names`` that is an iso-level."""
    for case in names:
        path, what = cases()[case]
        if "level" in what:
            yield case, path, what


def pipeline_rows(names: list[str], repeats: int, fresh_repeats: int) -> list[list[Any]]:
    """One row per threshold case: the measuring job's added time, warm and fresh."""
    from common import median, round_robin

    rows = []
    for case, path, what in threshold_cases(names):
        candidates = {
            "measured": partial(run_pipeline, path, what, True),
            "plain": partial(run_pipeline, path, what, False),
        }
        round_robin(candidates, 1)  # untimed: kernels loaded, caches warm
        seconds, last = round_robin(candidates, repeats)
        whole: dict[str, list[float]] = {"measured": [], "plain": []}
        figures = set()
        for _ in range(fresh_repeats):
            for impl in whole:
                begun = time.perf_counter()
                got = fresh(case, f"pipeline-{impl}", "")
                whole[impl].append(time.perf_counter() - begun)
                if impl == "measured":
                    figures.add((got["max_mm"], got["mean_mm"]))
        same = figures == {(last["measured"]["max_mm"], last["measured"]["mean_mm"])}
        warm_m, warm_p = median(seconds["measured"]), median(seconds["plain"])
        fresh_m, fresh_p = median(whole["measured"]), median(whole["plain"])
        rows.append(
            [
                case,
                last["measured"]["triangles"],
                warm_p,
                warm_m,
                100.0 * (warm_m - warm_p) / warm_m,
                fresh_p,
                fresh_m,
                100.0 * (fresh_m - fresh_p) / fresh_m,
                last["measured"]["max_mm"],
                last["measured"]["mean_mm"],
                "yes" if same else "no",
            ]
        )
        print(rows[-1], flush=True)
    return rows


PIPELINE_HEADER = [
    "case",
    "triangles",
    "unmeasured s (warm)",
    "measured s (warm)",
    "added % (warm)",
    "unmeasured s (fresh process)",
    "measured s (fresh process)",
    "added % (fresh)",
    "max mm",
    "mean mm",
    "same figures fresh",
]


def default_rows(names: list[str], repeats: int, fresh_repeats: int) -> list[list[Any]]:
    """One row per threshold case: the default job warm and fresh, its check's share."""
    from common import median

    rows = []
    for case, path, what in threshold_cases(names):
        run_default(path, what)  # untimed: kernels loaded
        warm_runs = [run_default(path, what) for _ in range(repeats)]
        fresh_runs = [fresh(case, "default", "") for _ in range(fresh_repeats)]
        last = warm_runs[-1]

        def med(runs: list[dict[str, Any]], key: str) -> float:
            return median([r[key] for r in runs])

        rows.append(
            [
                case,
                last["triangles"],
                f"{last['rounds']} ({last['finished_with']})",
                med(warm_runs, "job_seconds"),
                med(warm_runs, "measure_seconds"),
                100.0 * med(warm_runs, "measure_seconds") / med(warm_runs, "job_seconds"),
                med(fresh_runs, "job_seconds"),
                med(fresh_runs, "measure_seconds"),
                100.0 * med(fresh_runs, "measure_seconds") / med(fresh_runs, "job_seconds"),
                last["max_mm"],
                last["bound_mm"],
            ]
        )
        print(markdown_table_row(rows[-1]), flush=True)
    return rows


DEFAULT_HEADER = [
    "case",
    "triangles",
    "rounds (finished by)",
    "job s (warm)",
    "check s (warm)",
    "share % (warm)",
    "job s (fresh)",
    "check s (fresh)",
    "share % (fresh)",
    "max mm",
    "bound mm",
]


def peer_rows(names: list[str], repeats: int) -> list[list[Any]]:
    """One row per threshold case and search: the measurement's 200,000 queries (the points
    MISS samples, a side each, to the other surface) answered by MISS's search, native and
    numba's, and by peer libraries' nearest-triangle queries: libigl's AABB tree
    (``igl.point_mesh_squared_distance``, float64) and FCPW's BVH (``fcpw.scene_3D``,
    float32). Each builds its structure on both surfaces and answers both sides, timed
    warm (after one untimed round), medians of ``repeats``; max and mean of the 200,000
    distances."""
    import numpy as np
    from common import median, round_robin

    from miss.measure import _native as measuring

    rows = []
    for case, path, what in threshold_cases(names):
        ((a, b, n),) = run_job(path, what)
        rng = np.random.default_rng(0)
        pa, pb = measuring._sample(a, n, rng), measuring._sample(b, n, rng)
        candidates = peer_searches(a, b, pa, pb)
        round_robin(candidates, 1)
        seconds, last = round_robin(candidates, repeats)
        for name in candidates:
            found = last[name]
            rows.append(
                [case, name, median(seconds[name]), float(found.max()), float(found.mean())]
            )
            print(rows[-1], flush=True)
    return rows


def peer_searches(a: Any, b: Any, pa: Any, pb: Any) -> dict[str, Callable[[], Any]]:
    """The searches of :func:`peer_rows`, each answering ``pa`` to ``b`` and ``pb`` to ``a``
    (the peers that are installed: ``.[bench]``)."""
    import numpy as np

    import miss.measure._jit as jitted
    from miss.measure import _native as measuring

    def native() -> Any:
        d_ab = measuring.distances(pa, measuring.native_grid(b), ordered=True)
        return np.concatenate([d_ab, measuring.distances(pb, measuring.native_grid(a))])

    def numba() -> Any:
        d_ab = jitted._grid_distances(pa, jitted.jit_grid(b), np.inf, True)
        return np.concatenate([d_ab, jitted._grid_distances(pb, jitted.jit_grid(a), np.inf)])

    searches: dict[str, Callable[[], Any]] = {"MISS native": native, "MISS numba": numba}
    try:
        import igl

        def libigl() -> Any:
            d_ab = igl.point_mesh_squared_distance(pa, b.vertices.astype(float), b.faces)[0]
            d_ba = igl.point_mesh_squared_distance(pb, a.vertices.astype(float), a.faces)[0]
            return np.sqrt(np.concatenate([d_ab, d_ba]))

        searches["libigl AABB"] = libigl
    except ImportError:
        pass
    try:
        import fcpw

        def closest(mesh: Any, points: Any) -> Any:
            scene = fcpw.scene_3D()
            scene.set_object_count(1)
            scene.set_object_vertices(mesh.vertices.astype(np.float32), 0)
            scene.set_object_triangles(mesh.faces.astype(np.int32), 0)
            scene.build(fcpw.aggregate_type.bvh_surface_area, True)
            found = fcpw.interaction_3D_list()
            p32 = points.astype(np.float32)
            scene.find_closest_points(p32, np.full(len(p32), np.inf, np.float32), found)
            return np.array([x.d for x in found])

        searches["FCPW BVH"] = lambda: np.concatenate([closest(b, pa), closest(a, pb)])
    except ImportError:
        pass
    return searches


PEER_HEADER = ["case", "search", "s (warm)", "max mm", "mean mm"]


def markdown_table_row(row: list[Any]) -> str:
    from common import markdown_table

    return markdown_table(DEFAULT_HEADER, [row])


def _scene_pairs(volume: Any, labels: str) -> list[Pair]:
    """A label map's job: every part's surfaces, caught where the scene would measure them
    (the stand-in answers at once, so the job is timed without its measurement)."""
    from dataclasses import replace

    import miss
    from miss.structures import labelmap

    pairs: list[Pair] = []

    def catch(report: Any, before: Any, after: Any, samples: int) -> Any:
        pairs.append((before, after, samples))
        return replace(report, max_error_mm=0.0, mean_error_mm=0.0)

    measured = labelmap.measured
    labelmap.measured = catch
    try:
        scene = miss.extract_scene(volume, labels=labels, reduce=REDUCE, measure=True)
    finally:
        labelmap.measured = measured
    miss.export(scene, "glb")
    miss.export(scene, "wrl")
    return pairs


def measure(pairs: list[Pair], deviation: Callable[..., Any]) -> tuple[float, float]:
    """Max and mean error (mm) over the pairs: the largest maximum, the mean of the means
    weighted by samples (one pair: its own figures)."""
    devs = [deviation(a, b, samples=n) for a, b, n in pairs]
    total = sum(d.samples for d in devs)
    return max(d.max_mm for d in devs), sum(d.mean_mm * d.samples for d in devs) / total


def old_module(before: str = BEFORE) -> ModuleType | None:
    """deviation.py as it was at ``before``, importable beside the new one (None without git)."""
    from common import CACHE

    path = CACHE / f"deviation_{before}.py"
    if not path.is_file():
        proc = subprocess.run(
            ["git", "show", f"{before}:src/miss/deviation.py"],
            cwd=HERE,
            capture_output=True,
            text=True,
            check=False,
        )
        if proc.returncode != 0:
            return None
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(proc.stdout)
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks itself up there
    spec.loader.exec_module(module)
    return module


# ----------------------------------------------------------------------------- fresh runs


def child(case: str, impl: str, before: str) -> dict[str, Any]:
    """In a fresh interpreter: the job, then the measurement with its remaining imports
    (``impl`` "default": the default job, its check inside; its clock counts the imports)."""
    path, what = cases()[case]
    if impl.startswith("pipeline-"):
        return run_command(path, what, impl == "pipeline-measured")
    if impl == "default":
        out = run_default(path, what)
        out["job_seconds"] = time.perf_counter() - START
        return out
    pairs = run_job(path, what)
    job_seconds = time.perf_counter() - START
    from common import peak_since, resident_peak, start_peak

    job_peak = resident_peak()
    baseline = start_peak()
    t0 = time.perf_counter()
    if impl == "old":
        old = old_module(before)
        assert old is not None
        deviation = old.deviation
    else:
        from miss.measure import deviation  # native here: numba is not loaded
    worst, mean = measure(pairs, deviation)
    return {
        "numba_loaded": "numba" in sys.modules,
        "job_seconds": job_seconds,
        "measure_seconds": time.perf_counter() - t0,
        "job_peak_mb": job_peak / 2**20,
        "measure_peak_mb": peak_since(baseline) / 2**20,
        "max_mm": worst,
        "mean_mm": mean,
    }


def fresh(case: str, impl: str, before: str) -> dict[str, Any]:
    proc = subprocess.run(
        [sys.executable, str(Path(__file__)), "--child", case, impl, "--before", before],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"measure.py --child {case} {impl} failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- the table


def warm(case: str, repeats: int, old: ModuleType | None) -> dict[str, Any]:
    """Job, new and old measurement round-robin in this process; medians and figures."""
    from common import median, round_robin

    from miss.measure import deviation, native_deviation

    path, what = cases()[case]
    pairs = run_job(path, what)
    candidates: dict[str, Callable[[], Any]] = {
        "job": lambda: run_job(path, what),
        "new": lambda: measure(pairs, deviation),  # numba's kernels: it is loaded here
        "native": lambda: measure(pairs, native_deviation),
    }
    if old is not None:
        candidates["old"] = lambda: measure(pairs, old.deviation)
    round_robin(candidates, 1)  # untimed: kernels loaded, caches warm
    seconds, last = round_robin(candidates, repeats)
    if last["native"] != last["new"]:
        raise AssertionError(f"{case}: native figures {last['native']} != {last['new']}")
    return {
        "job_seconds": median(seconds["job"]),
        "new_seconds": median(seconds["new"]),
        "native_seconds": median(seconds["native"]),
        "old_seconds": median(seconds["old"]) if old is not None else None,
        "new": last["new"],
        "native": last["native"],
        "old": last.get("old"),
        "triangles": sum(a.n_triangles for a, _, _ in pairs),
        "parts": len(pairs),
    }


def row(case: str, w: dict[str, Any], f: dict[str, list[dict[str, Any]]]) -> list[Any]:
    def med(impl: str, key: str) -> float:
        runs = f.get(impl) or []
        return statistics.median(r[key] for r in runs) if runs else float("nan")

    def share(measure_s: float, job_s: float) -> float:
        return 100.0 * measure_s / (job_s + measure_s)

    old = w["old"] or (float("nan"), float("nan"))
    return [
        case,
        w["triangles"],
        w["job_seconds"],
        w["new_seconds"],
        w["native_seconds"],
        w["old_seconds"] if w["old_seconds"] is not None else float("nan"),
        share(w["new_seconds"], w["job_seconds"]),
        med("new", "job_seconds"),
        med("new", "measure_seconds"),
        med("old", "measure_seconds"),
        share(med("new", "measure_seconds"), med("new", "job_seconds")),
        w["new"][0],
        old[0],
        w["new"][1],
        old[1],
        med("new", "job_peak_mb"),
        med("new", "measure_peak_mb"),
        med("old", "measure_peak_mb"),
    ]


HEADER = [
    "case",
    "triangles",
    "job s (warm)",
    "measure s (warm)",
    "native measure s (warm)",
    "old measure s (warm)",
    "share % (warm)",
    "job s (fresh)",
    "measure s (fresh)",
    "old measure s (fresh)",
    "share % (fresh)",
    "max mm",
    "old max mm",
    "mean mm",
    "old mean mm",
    "job peak MB",
    "measure peak MB",
    "old measure peak MB",
]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--fresh-repeats", type=int, default=5)
    parser.add_argument("--cases", default=",".join(cases()), help="comma-separated names")
    parser.add_argument("--out", type=Path, default=None, help="folder for measure.{json,md}")
    parser.add_argument("--before", default=BEFORE, help="git ref of the old deviation.py")
    parser.add_argument("--child", nargs=2, metavar=("CASE", "IMPL"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(*args.child, args.before)))
        return 0

    from common import RESULTS, markdown_table, save

    names = [c for c in args.cases.split(",") if c]
    unknown = sorted(set(names) - set(cases()))
    if unknown:
        parser.error(f"unknown case(s) {', '.join(unknown)}; choose from {', '.join(cases())}")
    old = old_module(args.before)
    rows, data = [], {}
    for case in names:
        w = warm(case, args.repeats, old)
        f: dict[str, list[dict[str, Any]]] = {"new": [], "old": []}
        for _ in range(args.fresh_repeats):
            for impl in ("new", "old") if old is not None else ("new",):
                f[impl].append(fresh(case, impl, args.before))
        rows.append(row(case, w, f))
        data[case] = {"warm": w, "fresh": f}
        print(markdown_table(HEADER, rows[-1:]), flush=True)
    default = default_rows(names, args.repeats, args.fresh_repeats)
    piped = pipeline_rows(names, args.repeats, args.fresh_repeats)
    peers = peer_rows(names, args.repeats)
    table = markdown_table(HEADER, rows)
    note = (
        f"\nShare = measurement / (job + measurement). Warm: medians of {args.repeats} "
        f"round-robin runs in one process; fresh: medians of {args.fresh_repeats} new "
        "interpreters each, new and old alternately (the job's time counts its imports, the "
        "measurement's its own). Old = deviation.py at "
        f"{args.before}. Peak: the job's VmHWM; the measurement's above the job's resident set.\n"
        "\nThe default job (guaranteed bound: quadric to 10 % within 0.002 of the diagonal; "
        "its check is the measurement, all rounds; share = check / whole job, which includes "
        f"it), medians of {args.repeats} warm and {args.fresh_repeats} fresh runs:\n\n"
        + markdown_table(DEFAULT_HEADER, default)
        + "\n"
        + "\nThe first table's job as MISS runs it, measured and not; added = (measured - "
        "unmeasured) / measured. Warm: `miss.pipeline.run` as the server's workers run it "
        "(numba loaded; the undecimated surface's half of the measurement made while it "
        f"decimates), medians of {args.repeats} round-robin runs in one process. Fresh: "
        "`miss convert` as a user runs it (a measured one measures on a thread with the "
        "native kernels, no numba started), medians of "
        f"{args.fresh_repeats} new interpreters each, alternately, "
        "timed from outside; same figures: the fresh runs' max and mean are the warm "
        "ones:\n\n" + markdown_table(PIPELINE_HEADER, piped) + "\n"
        "\nThe measurement's 200,000 nearest-triangle queries (the points MISS samples, to "
        "the other surface, both ways), each search building its structure on both surfaces: "
        f"warm medians of {args.repeats}; max and mean of the distances:\n\n"
        + markdown_table(PEER_HEADER, peers)
        + "\n"
    )
    print(table + note)
    result = {
        "cases": data,
        "header": HEADER,
        "rows": rows,
        "default": default,
        "pipeline": piped,
        "peers": peers,
    }
    save("measure", result, table + note, args.out or RESULTS)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(HERE))
    sys.exit(main())
