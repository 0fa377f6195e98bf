"""Blockwise surfaces at scale: one VTK flying-edges pass over the whole array against
MISS's blockwise surface on a local Dask cluster of 1 and 2 workers.

    .venv/bin/python benchmarks/scale.py [--size 512,512,600] [--runs 3] [--block 128]
    .venv/bin/python benchmarks/scale.py --size 1024,1024,1200     # the issue's size
    .venv/bin/python benchmarks/scale.py --crossover               # threads vs cluster

The volume is the CThead (``$MISS_CTHEAD``, else ../shared/datasets beside the repo)
resampled (linear, int16) to ``--size`` and stored as MISS stores a volume (Zarr, chunks
of 64³) in a temporary folder. Every variant runs in its own process, watched from outside (psutil, every 20 ms):
the peak resident memory of each process of its tree (the job's own, each worker's, each
nanny's) and of the tree together. The interpreter's baseline is a process that imports
the same modules and stops. VTK runs on one thread everywhere
(``VTK_SMP_BACKEND_IN_USE=Sequential``), so that workers are the only parallelism; one
more row gives the single pass on both cores (STDThread). Times are medians of ``--runs``.

Writes ``results/scale.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
LEVEL = 1500.0  # bone
#: Jobs after a cluster's first, their median reported: one job's time on 2 shared cores
#: varies by 20 % from run to run.
NEXT_JOBS = 3


def _cthead() -> Path:
    env = os.environ.get("MISS_CTHEAD")
    if env:
        return Path(env)
    repo = Path(__file__).resolve().parents[1]
    for root in (repo.parent / "shared", repo.parents[1] / "shared"):
        path = root / "datasets" / "ct_head_stanford_cthead" / "CThead.nhdr"
        if path.is_file():
            return path
    raise SystemExit("CThead not found: set MISS_CTHEAD to CThead.nhdr")


def _axis(data: np.ndarray, axis: int, count: int) -> np.ndarray:
    """Linear resampling along ``axis`` to ``count`` samples (same extent), int16 kept."""
    old = data.shape[axis]
    pos = np.linspace(0.0, old - 1.0, count)
    low = np.minimum(np.floor(pos).astype(np.int64), old - 2)
    shape_f = [1, 1, 1]
    shape_f[axis] = count
    frac = (pos - low).astype(np.float32).reshape(shape_f)
    a = np.take(data, low, axis).astype(np.float32)
    b = np.take(data, low + 1, axis).astype(np.float32)
    return np.asfortranarray(np.rint(a + frac * (b - a)).astype(data.dtype))


def make_volume(size: tuple[int, int, int], folder: Path) -> Path:
    """CThead resampled to ``size``, int16, stored as MISS stores a volume (Zarr in
    chunks of 64³, :func:`miss.server.storage.chunked.write_planes`), plane by plane."""
    from miss.io import load_volume
    from miss.server.storage import chunked

    path = folder / f"cthead_{'x'.join(map(str, size))}.zarr"
    if (path / "zarr.json").is_file():
        return path
    data = load_volume(_cthead()).data
    data = _axis(_axis(data, 0, size[0]), 1, size[1])  # (X, Y, 113): small
    attributes = {"affine": np.eye(4).tolist(), "provenance": {"benchmark": "scale.py"}}
    chunked.write_planes(path, size, data.dtype, _planes(data, size[2]), attributes)
    return path


def _planes(data: np.ndarray, count: int) -> Iterator[np.ndarray]:
    """The (X, Y) planes of ``data`` linearly resampled to ``count`` along z, one by one."""
    old = data.shape[2]
    for z in np.linspace(0.0, old - 1.0, count):
        k = min(int(z), old - 2)
        a, b = data[:, :, k].astype(np.float32), data[:, :, k + 1].astype(np.float32)
        yield np.rint(a + np.float32(z - k) * (b - a)).astype(data.dtype)


# ---- the variants, each run as ``scale.py --variant NAME --zarr PATH`` in a child ----


def _variant(name: str, zarr_path: str, block: int) -> dict[str, Any]:
    if name.startswith("spin"):  # the control: no volume, no MISS
        return _spin_at_once(int(name.removeprefix("spin")))
    import miss.surface.blockwise  # noqa: F401  (the same imports as the baseline)
    from miss.server.storage import chunked
    from miss.types import Volume

    array = chunked.open_array(Path(zarr_path))[0]
    if name == "baseline":
        import distributed  # noqa: F401

        return {}
    if name.startswith("single"):
        return _single(array)
    if name == "threads":
        from miss.surface.blockwise import blockwise_surface

        start = time.perf_counter()
        mesh = blockwise_surface(Volume(array, np.eye(4)), LEVEL, normals=False, block=block,
                                 cluster=False)  # fmt: skip
        return {"seconds": time.perf_counter() - start, "triangles": mesh.n_triangles}
    if name.startswith("job"):
        return _job(Volume(array, np.eye(4)), two_stage=name == "job")
    workers = int(name.removeprefix("blocks"))
    return _blocks(Volume(array, np.eye(4)), workers, block)


#: The control's work: a loop of pure Python arithmetic, which stays in the core's own
#: caches (about 3 s on this machine). It shows what two processes at once get from the
#: machine when neither touches memory nor waits for the other.
SPIN = "s = 0\nfor i in range(20_000_000):\n    s += i * i\n"


def _spin_at_once(count: int) -> dict[str, Any]:
    """``count`` processes of :data:`SPIN` started together; seconds until the last ends."""
    start = time.perf_counter()
    procs = [subprocess.Popen([sys.executable, "-S", "-c", SPIN]) for _ in range(count)]
    for proc in procs:
        proc.wait()
    return {"seconds": time.perf_counter() - start, "triangles": 0}


def _single(array: Any) -> dict[str, Any]:
    from miss.surface import _flying_edges

    start = time.perf_counter()
    data = np.asarray(array)  # (X, Y, Z) Fortran order: the stored (Z, Y, X), transposed
    read = time.perf_counter() - start
    start = time.perf_counter()
    _, faces, _ = _flying_edges(data, LEVEL - 0.25, normals=False)
    return {"seconds": time.perf_counter() - start, "read": read, "triangles": len(faces)}


def _blocks(volume: Any, workers: int, block: int) -> dict[str, Any]:
    from distributed import Client

    from miss.surface.blockwise import blockwise_surface
    from miss.surface.runner import local_cluster

    start = time.perf_counter()
    with local_cluster(workers) as cluster:  # the cluster MISS itself starts
        up = time.perf_counter() - start
        times = []
        for _ in range(1 + NEXT_JOBS):  # a new cluster's first job, then the next ones on it
            with Client(cluster) as client:
                client.run(_forget_chunks)  # each job decompresses its chunks afresh
            start = time.perf_counter()
            mesh = blockwise_surface(
                volume, LEVEL, normals=False, block=block, scheduler=cluster.scheduler_address
            )
            times.append(time.perf_counter() - start)
    return {
        "seconds": times[0],
        "next_job": statistics.median(times[1:]),
        "cluster_start": up,
        "triangles": mesh.n_triangles,
    }


def _forget_chunks() -> None:
    from miss.surface.blocks import CHUNKS

    with CHUNKS.lock:
        CHUNKS.chunks.clear()
        CHUNKS.held = 0


class _Clock:
    """A sink as the server's: a preview, levels of detail over 2 M triangles, the GLB;
    notes when each arrives (seconds since the job started)."""

    wants_preview = True
    lod_triangles = 2_000_000

    def __init__(self) -> None:
        self.start = time.perf_counter()
        self.at: dict[str, float] = {}

    def _seen(self, what: str) -> None:
        self.at.setdefault(what, time.perf_counter() - self.start)

    def put(self, fmt: str, data: bytes) -> None:
        self._seen(fmt)

    def put_lod(self, files: Any) -> None:
        self._seen("lod")

    def deliver(self, result: Any) -> None:
        return None


def _job(volume: Any, two_stage: bool) -> dict[str, Any]:
    """The job a user starts (level, the default decimation, GLB), as the server runs it:
    when its preview, its levels of detail (a model over 2 M triangles) and its GLB were
    ready. ``two_stage`` False: the welded full-resolution surface decimated whole, as
    before blocks were decimated where they were made."""
    from miss.pipeline import run
    from miss.spec import JobSpec
    from miss.structures import build

    if not two_stage:
        build._blocks_decimate = lambda item, decimation: False  # type: ignore[assignment]

    clock = _Clock()
    result = run(volume, JobSpec.of(level=LEVEL, formats=("glb",)), sink=clock, measure=False)
    return {
        "seconds": time.perf_counter() - clock.start,
        "at": clock.at,
        "triangles": result.scene.n_triangles,
        "max_mm": result.report.max_error_mm,
        "stages": result.seconds,
    }


def _threads(volume: Any, block: int, cluster: bool) -> float:
    from miss.surface.blockwise import blockwise_surface

    start = time.perf_counter()
    blockwise_surface(volume, LEVEL, normals=False, block=block, cluster=cluster)
    return time.perf_counter() - start


# ---- the parent: runs and watches the children ----


def watch(args: list[str], env: dict[str, str]) -> dict[str, Any]:
    """Run ``scale.py args`` in a child; its JSON answer, the peak RSS (MB) of each process
    of its tree by role, and of the tree together."""
    import psutil
    from common import tree_rss  # here: the measured child imports none of it

    proc = subprocess.Popen(
        [sys.executable, __file__, *args], stdout=subprocess.PIPE, text=True, env=env
    )
    root = psutil.Process(proc.pid)
    peaks: dict[int, float] = {}
    roles: dict[int, str] = {}

    def seen(p: Any, rss: float) -> None:
        roles.setdefault(p.pid, _role(p, root))
        peaks[p.pid] = max(peaks.get(p.pid, 0.0), rss)

    total = tree_rss(proc, seen)
    out, _ = proc.communicate()
    if proc.returncode != 0:
        raise SystemExit(f"variant {args} failed (exit {proc.returncode})")
    by_role: dict[str, float] = {}
    for pid, peak in peaks.items():
        by_role[roles[pid]] = max(by_role.get(roles[pid], 0.0), peak)
    return {**json.loads(out.strip().splitlines()[-1]), "peak_mb": by_role, "total_mb": total}


def _role(p: Any, root: Any) -> str:
    if p.pid == root.pid:
        return "job"
    cmd = " ".join(p.cmdline())
    if "multiprocessing" in cmd and "spawn" in cmd:
        return "worker"  # nanny's child
    return "other"


def _env(threads: str = "Sequential") -> dict[str, str]:
    src = str(Path(__file__).resolve().parents[1] / "src")
    return {**os.environ, "PYTHONPATH": src, "VTK_SMP_BACKEND_IN_USE": threads}


def main_table(size: tuple[int, int, int], runs: int, block: int, folder: Path) -> str:
    path = str(make_volume(size, folder))
    base = watch(["--variant", "baseline", "--zarr", path], _env())["peak_mb"]["job"]
    variants = [
        ("single pass, VTK flying edges, whole array (1 thread)", "single", _env()),
        ("single pass, VTK flying edges, whole array (2 threads)", "single", _env("STDThread")),
        ("MISS blockwise, 1 worker", "blocks1", _env()),
        ("MISS blockwise, 2 workers", "blocks2", _env()),
        ("MISS blockwise, threads in the job (VTK on 2 threads)", "threads", _env("STDThread")),
    ]
    # the control: the same work once in one process and in each of two at once
    controls = [("spin1", _env()), ("spin2", _env())]
    # round by round, every variant in each: a slow spell of the machine meets them all
    rounds, spins = [], []
    for _ in range(runs):
        rounds.append(
            [watch(["--variant", name, "--zarr", path, "--block", str(block)], env) for _, name, env in variants]
        )  # fmt: skip
        spins.append([watch(["--variant", name], env)["seconds"] for name, env in controls])
    rows = []
    for k, (label, _, _) in enumerate(variants):
        done = [one[k] for one in rounds]
        seconds = statistics.median(d["seconds"] for d in done)
        peak = {role: max(d["peak_mb"].get(role, 0.0) for d in done) for role in done[0]["peak_mb"]}
        total = max(d["total_mb"] for d in done)
        read = statistics.median(d.get("read", 0.0) for d in done)
        rows.append((label, seconds, read, peak, total, done[0]["triangles"]))
        print(label, f"{seconds:.2f} s", peak, f"total {total:.0f} MB", file=sys.stderr)
        if "next_job" in done[0]:  # the workers warm, the chunks decompressed afresh
            again = statistics.median(d["next_job"] for d in done)
            rows.append((f"{label}, next job", again, 0.0, peak, total, done[0]["triangles"]))
    jobs = []
    for label, name in (
        ("blocks decimated where they were made, then across them", "job"),
        ("the welded full-resolution surface decimated whole (before)", "job1"),
    ):
        done = [watch(["--variant", name, "--zarr", path], _env("STDThread")) for _ in range(runs)]
        jobs.append((label, done))
        print(label, [round(d["seconds"], 2) for d in done], file=sys.stderr)
    ratios = {
        key: statistics.median(one[2][key] / one[3][key] for one in rounds)
        for key in ("seconds", "next_job")
    }  # 1 worker against 2, round by round
    ratios["vtk"] = statistics.median(one[0]["seconds"] / one[1]["seconds"] for one in rounds)
    # two processes' work in the time of ... : 2 x one's time / the pair's
    ratios["spin"] = statistics.median(2 * one / two for one, two in spins)
    ratios["spins"] = sorted(2 * one / two for one, two in spins)
    return _markdown(size, block, runs, base, rows, ratios) + _job_markdown(base, jobs)


def _job_markdown(base: float, jobs: list[tuple[str, list[dict[str, Any]]]]) -> str:
    lines = [
        "",
        "The job a user starts on it (level 1500, the default decimation: quadric to 90 % "
        "within 0.002 of the diagonal, GLB), run as the server runs it (a sink that wants "
        "a preview and levels of detail over 2 M triangles; blocks of 128 on threads below "
        "1 G voxels, else a local cluster); seconds from the job's start, medians. The max error "
        "is the report's: measured on the whole mesh, or for blocks decimated where they "
        "were made the two stages' measured maxima added (at most that):",
        "",
        "| decimation | preview ready | levels of detail ready | GLB ready | surface | "
        "decimate | triangles | max error mm | peak RSS - base (MB) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for label, done in jobs:
        at = [d["at"] for d in done]

        def med(key: str, at: list[dict[str, float]] = at) -> str:
            seen = [a[key] for a in at if key in a]
            return f"{statistics.median(seen):.2f}" if seen else "-"

        stage = {
            k: statistics.median(d["stages"].get(k, 0.0) for d in done)
            for k in ("surface", "decimate")
        }
        peak = max(max(d["peak_mb"].values()) for d in done) - base
        lines.append(
            f"| {label} | {med('preview')} | {med('lod')} | {med('glb')} "
            f"| {stage['surface']:.2f} | {stage['decimate']:.2f} | {done[0]['triangles']:,} "
            f"| {done[0]['max_mm']:.3f} | {peak:.0f} |"
        )
    return "\n".join(lines) + "\n"


def _markdown(
    size: tuple[int, int, int],
    block: int,
    runs: int,
    base: float,
    rows: list[Any],
    ratios: dict[str, float],
) -> str:
    single = rows[0][1] + rows[0][2]
    lines = [
        f"Volume {size[0]}x{size[1]}x{size[2]} int16 ({np.prod(size) / 1e6:.0f} M voxels, "
        f"{np.prod(size) * 2 / 2**30:.2f} GiB) on Zarr, level {LEVEL:g}, blocks of {block}, "
        f"median of {runs} run(s); {os.cpu_count()} cores. Interpreter baseline "
        f"{base:.0f} MB (numpy, VTK, zarr, distributed imported). Peak RSS above it per "
        "process: job = the calling process, worker = each Dask worker (its nanny is "
        "smaller); total = the whole process tree at its largest.",
        "",
        "The single pass's time is the contour alone; its read (the whole Zarr array into "
        "one F-ordered numpy array) is the next column. Blockwise times include all "
        "reading (int16: one pass, each block's value range checked at the end), the "
        "welding and the mapping to mm, not the cluster's start. A cluster's first job "
        "meets new worker processes (first use of VTK, memory touched for the first "
        f"time); 'next job' is the median of the {NEXT_JOBS} jobs after it on the same "
        "cluster, their chunk caches emptied first, as a job on another volume would find "
        "them. The read is the whole "
        "array's, through MISS's reader of the chunk files.",
        "",
        "| variant | time (s) | + read (s) | vs single + read | job peak - base (MB) "
        "| worker peak - base (MB) | total peak (MB) | triangles |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for label, seconds, read, peak, total, triangles in rows:
        worker = peak.get("worker")
        lines.append(
            f"| {label} | {seconds:.2f} | {read:.2f} | {(seconds + read) / single:.2f}x "
            f"| {peak['job'] - base:.0f} "
            f"| {'-' if worker is None else f'{worker - base:.0f}'} | {total:.0f} "
            f"| {triangles:,} |"
        )
    lines += [
        "",
        f"2 workers against 1: {ratios['seconds']:.2f}x faster on a new cluster's first "
        f"job, {ratios['next_job']:.2f}x on the next (medians of the rounds' ratios: each "
        "round runs every variant once, in the table's order). The machine's own ceiling "
        f"for two at once: VTK's single pass on 2 threads against 1, {ratios['vtk']:.2f}x; "
        "two processes of pure arithmetic that touch no memory (the control, "
        "`scale.py --variant spin1|spin2`, once a round), started together, did twice one's "
        f"work {ratios['spin']:.2f}x as fast as one did it once (rounds: "
        f"{', '.join(f'{r:.2f}' for r in ratios['spins'])}x).",
    ]
    return "\n".join(lines) + "\n"


def crossover(folder: Path, block: int) -> str:
    """Threads against a LocalCluster (its start included) as the volume grows."""
    sizes = [(256, 256, 113), (512, 512, 113), (512, 512, 226), (512, 512, 452)]
    lines = [
        "| voxels (M) | threads (s) | local cluster, 2 workers, start included (s) |",
        "|---:|---:|---:|",
    ]
    for size in sizes:
        path = str(make_volume(size, folder))
        out = subprocess.run(
            [sys.executable, __file__, "--variant", "crossover", "--zarr", path,
             "--block", str(block)],
            capture_output=True, text=True, env=_env(), check=True,
        ).stdout  # fmt: skip
        t = json.loads(out.strip().splitlines()[-1])
        lines.append(f"| {np.prod(size) / 1e6:.0f} | {t['threads']:.2f} | {t['cluster']:.2f} |")
        print(lines[-1], file=sys.stderr)
    return "\n".join(lines) + "\n"


def _crossover_child(zarr_path: str, block: int) -> dict[str, Any]:
    from miss.server.storage import chunked
    from miss.types import Volume

    volume = Volume(chunked.open_array(Path(zarr_path))[0], np.eye(4))
    return {"threads": _threads(volume, block, False), "cluster": _threads(volume, block, True)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", default="512,512,600", help="X,Y,Z voxels")
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--block", type=int, default=128, help="block edge, voxels")
    parser.add_argument("--crossover", action="store_true", help="threads vs local cluster")
    parser.add_argument("--folder", default=None, help="where the Zarr volumes go")
    parser.add_argument("--variant", help=argparse.SUPPRESS)
    parser.add_argument("--zarr", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.variant == "crossover":
        print(json.dumps(_crossover_child(args.zarr, args.block)))
        return
    if args.variant:
        print(json.dumps(_variant(args.variant, args.zarr, args.block)))
        return
    size = tuple(int(v) for v in args.size.split(","))
    with tempfile.TemporaryDirectory(dir=args.folder) as tmp:
        if args.crossover:
            text = crossover(Path(tmp), args.block)
            name = "scale_crossover.md"
        else:
            text = main_table(size, args.runs, args.block, Path(tmp))  # type: ignore[arg-type]
            name = (
                "scale.md"
                if args.size == "512,512,600"
                else f"scale_{args.size.replace(',', 'x')}.md"
            )
    print(text)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / name).write_text(text)


if __name__ == "__main__":
    main()
