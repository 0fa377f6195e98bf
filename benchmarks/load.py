"""Load on a real ``miss serve``: 50 viewers, 4 conversion jobs and a large upload at once.

    .venv/bin/python benchmarks/load.py [--seconds 35] [--viewers 50] [--think 1.0]

The server runs as a subprocess on a free loopback port with a temporary data folder and
2 job workers. Setup (not measured): the account ``ana`` uploads the CThead
(256 x 256 x 225) and 3 models of it are made. Then, for ``--seconds``:

- ``--viewers`` viewers (one process, asyncio + aiohttp, a session of their own each, half
  ``ana``'s and half the administrator's) loop: the GLB of one of the models (every other
  time with ``If-None-Match``, so 304), 3 slice PNGs (scrubbing), the model's JSON; then
  a pause of ``--think`` s on average (a person looks at what they fetched).
- 2 s in, 4 jobs with parameters not made before (2 by ``ana``, 2 by the administrator:
  the limit is 2 queued or running per account).
- when the jobs are done (at the latest halfway), ``ana`` uploads a 384 x 384 x 500 CThead
  (147 MB NIfTI).
- a probe (its own process) asks ``GET /api/health`` (answered on the event loop) every
  50 ms; its latency is the loop's, split by what ran at the time.

The viewers, the probe and the driver start together once all three processes are
ready. Cached model fetches are also reported per phase (during the jobs, during the
upload, viewers only). The viewers' own CPU time is reported: on a 2-core machine the
load generator shares the cores with the server and must not be what limits the run.

All requests come from 127.0.0.1 and the viewers are logged in, so the API's rate limit
(20/s per account, bursts of 200) is raised for the run (``MISS_API_RATE`` and
``MISS_API_BURST`` = 10^6): its check still runs on every request, it just never refuses.

On PostgreSQL (``--database postgres``: a throw-away cluster, as the tests start one)
the run can be repeated with several server processes (``--processes 1,2``: ``miss serve
--processes N`` on one port); ``--backup`` takes ``miss backup`` while the jobs run,
restores it into a fresh folder and database after the run and compares every row and
file with the source (rows a job changed after the backup excepted).

Writes ``results/load.{json,md}`` (``results/load_postgres.{json,md}`` on PostgreSQL);
exits 1 if any request failed or the restored copy differs.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing as mp
import os
import random
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
from common import markdown_table, paper_volume_file, save

PASSWORD = "load-benchmark-password"
SETUP_MODELS = (
    {"level": 1500.0},  # bone, quadric decimation (the defaults)
    {"level": 600.0},  # skin
    {"level": 1500.0, "sample_rate": 2, "decimate": "none"},
)
LOAD_JOBS = (
    ("ana", {"level": 1000.0}),
    ("ana", {"level": 1200.0, "decimate": "schroeder"}),
    ("admin", {"level": 800.0}),
    ("admin", {"level": 1400.0, "sample_rate": 2}),
)
UPLOAD_SHAPE = (384, 384, 500)
PROBE_EVERY = 0.05
#: Seconds any request may take before it counts as failed (the server is loaded on purpose).
TIMEOUT = 120.0
#: Seconds from the moment all load processes are ready to the measured start.
LEAD = 0.5
VIEWER_CLASSES = ("model fetch cached", "model fetch 304", "slice", "metadata")


# -- the server -------------------------------------------------------------------------


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stop_server(proc: subprocess.Popen[bytes], timeout: float = 30) -> None:
    """Stop a server :func:`start_server` started: SIGTERM, then SIGKILL if it has not
    exited within ``timeout`` seconds."""
    proc.terminate()
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def start_server(
    data_dir: Path,
    workers: int = 2,
    database: str = "",
    processes: int = 1,
    env: dict[str, str] | None = None,
) -> tuple[subprocess.Popen[bytes], str]:
    port = free_port()
    env = {
        **os.environ,
        **({"MISS_DATABASE_URL": database} if database else {}),
        "MISS_DATA_DIR": str(data_dir),
        "MISS_ADMIN_PASSWORD": PASSWORD,
        "MISS_DEMO": "0",
        "MISS_WORKERS": str(workers),
        "MISS_API_RATE": "1000000",
        "MISS_API_BURST": "1000000",
        **(env or {}),
    }
    cmd = [sys.executable, "-m", "miss.cli", "serve", "--port", str(port)]
    cmd += ["--processes", str(processes)]
    log = open(data_dir.parent / "server.log", "wb")  # noqa: SIM115 (the server's lifetime)
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(
                f"miss serve exited:\n{(data_dir.parent / 'server.log').read_text()}"
            )
        try:
            if httpx.get(url + "/api/health", timeout=2).status_code == 200:
                return proc, url
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    raise RuntimeError("miss serve did not start within 90 s")


def log_in(url: str, name: str, password: str = PASSWORD) -> dict[str, str]:
    body = {"username": name, "password": password}
    r = httpx.post(url + "/api/auth/login", json=body, timeout=TIMEOUT)
    r.raise_for_status()
    return {"Authorization": f"Bearer {r.json()['token']}"}


def upload(url: str, headers: dict[str, str], path: Path) -> dict[str, Any]:
    with open(path, "rb") as f:
        r = httpx.post(
            url + "/api/volumes", files={"file": (path.name, f)}, headers=headers, timeout=900
        )
    assert r.status_code == 201, r.text
    return r.json()


def submit(url: str, headers: dict[str, str], volume: str, params: dict[str, Any]) -> str:
    body = {"volume": volume, **params}
    r = httpx.post(url + "/api/models", json=body, headers=headers, timeout=TIMEOUT)
    assert r.status_code in (200, 202), r.text
    return r.json()["id"]


def wait_done(url: str, headers: dict[str, str], model_id: str, timeout: float = 600) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        model = httpx.get(f"{url}/api/models/{model_id}", headers=headers, timeout=TIMEOUT).json()
        if model["status"] in ("done", "failed"):
            assert model["status"] == "done", model
            return model
        time.sleep(0.25)
    raise RuntimeError(f"model {model_id} not done after {timeout} s")


def setup(url: str, viewers: int) -> dict[str, Any]:
    """ana and her CThead, 3 finished models, a session per viewer."""
    admin = log_in(url, "admin")
    body = {"name": "ana", "password": PASSWORD}
    r = httpx.post(url + "/api/users", json=body, headers=admin, timeout=TIMEOUT)
    r.raise_for_status()
    ana = log_in(url, "ana")
    volume = upload(url, ana, paper_volume_file())
    models = [submit(url, ana, volume["id"], p) for p in SETUP_MODELS[:2]]
    models += [submit(url, admin, volume["id"], p) for p in SETUP_MODELS[2:]]
    for model_id in models:
        wait_done(url, admin, model_id)
    sessions = [log_in(url, "ana" if i % 2 else "admin") for i in range(viewers)]
    return {
        "admin": admin,
        "ana": ana,
        "volume": volume["id"],
        "models": models,
        "sessions": sessions,
        "views": {axis: view["count"] for axis, view in volume["views"].items()},
    }


# -- the viewers and the probe (each in a process of its own) ----------------------------


def synced_start(cfg: dict[str, Any], ready: Any) -> None:
    """Wait until the viewers, the probe and the driver are all ready (a process takes
    seconds to start and import); then each sets the same ``start`` and ``end``."""
    ready.wait(timeout=120)
    cfg["start"] = time.monotonic() + LEAD  # one clock for all: CLOCK_MONOTONIC
    cfg["end"] = cfg["start"] + cfg["seconds"]


def viewers_main(cfg: dict[str, Any], ready: Any, out: str) -> None:
    samples = asyncio.run(_viewers(cfg, ready))
    cpu = time.process_time()  # this process's own CPU: it must not be what limits the run
    Path(out).write_text(json.dumps({"samples": samples, "cpu_s": cpu}))


async def _viewers(cfg: dict[str, Any], ready: Any) -> list[tuple[Any, ...]]:
    # aiohttp rather than httpx here: its C parser takes a fraction of the CPU per
    # request, and on a 2-core machine the load generator shares the cores with the server.
    import aiohttp

    samples: list[tuple[Any, ...]] = []
    n = len(cfg["sessions"])
    timeout = aiohttp.ClientTimeout(total=TIMEOUT)
    connector = aiohttp.TCPConnector(limit=2 * n)
    async with aiohttp.ClientSession(cfg["url"], timeout=timeout, connector=connector) as http:
        synced_start(cfg, ready)
        await asyncio.sleep(max(0.0, cfg["start"] - time.monotonic()))
        await asyncio.gather(*(_viewer(http, cfg, i, samples) for i in range(n)))
    return samples


async def _viewer(http: Any, cfg: dict[str, Any], n: int, samples: list[tuple[Any, ...]]) -> None:
    """One person: model (alternately fresh and revalidated), 3 slices, the model's JSON."""
    rng = random.Random(n)
    session = cfg["sessions"][n]
    await asyncio.sleep(rng.uniform(0, cfg["think"]))  # not all at the same instant
    model, etag, i = rng.choice(cfg["models"]), "", 0
    while time.monotonic() < cfg["end"]:
        path = f"/api/models/{model}/model.glb"
        if i % 2 and etag:  # the same model again, as a browser with it in its cache
            await _timed(
                http, samples, "model fetch 304", path, session | {"If-None-Match": etag}, 304
            )
        else:
            model = rng.choice(cfg["models"])
            path = f"/api/models/{model}/model.glb"
            etag = await _timed(http, samples, "model fetch cached", path, session, 200)
        for _ in range(cfg["slices"]):
            axis = rng.choice(sorted(cfg["views"]))
            index = rng.randrange(cfg["views"][axis])
            path = f"/api/volumes/{cfg['volume']}/slices/{axis}/{index}.png"
            await _timed(http, samples, "slice", path, session, 200)
        await _timed(http, samples, "metadata", f"/api/models/{model}", session, 200)
        await asyncio.sleep(rng.uniform(0.5, 1.5) * cfg["think"])
        i += 1


async def _timed(
    http: Any,
    samples: list[tuple[Any, ...]],
    kind: str,
    path: str,
    headers: dict[str, str],
    expect: int,
) -> str:
    """GET ``path`` (whole body read); records (kind, start, seconds, ok, status or error);
    returns the response's ETag ("" when none or on error)."""
    import aiohttp

    t0 = time.monotonic()
    try:
        async with http.get(path, headers=headers) as r:
            await r.read()
            status, etag = r.status, r.headers.get("etag", "")
    except (aiohttp.ClientError, TimeoutError) as exc:
        samples.append((kind, t0, time.monotonic() - t0, False, type(exc).__name__))
        return ""
    samples.append((kind, t0, time.monotonic() - t0, status == expect, status))
    return etag


def probe_main(cfg: dict[str, Any], ready: Any, stop: Any, out: str) -> None:
    """``GET /api/health`` every ``PROBE_EVERY`` s until ``stop`` is set."""
    samples = []
    with httpx.Client(base_url=cfg["url"], timeout=TIMEOUT) as http:
        synced_start(cfg, ready)
        time.sleep(max(0.0, cfg["start"] - time.monotonic()))
        tick = time.monotonic()
        while not stop.is_set():
            t0 = time.monotonic()
            try:
                ok = http.get("/api/health").status_code == 200
            except httpx.HTTPError:
                ok = False
            samples.append((t0, time.monotonic() - t0, ok))
            tick += PROBE_EVERY
            time.sleep(max(0.0, tick - time.monotonic()))
    Path(out).write_text(json.dumps(samples))


# -- jobs and the upload (in the main process) -------------------------------------------


def run_jobs(url: str, env: dict[str, Any], jobs: list[dict[str, Any]]) -> None:
    """Submit the load's jobs at once; note when each is seen done (or what went wrong)."""
    try:
        _run_jobs(url, env, jobs)
    except Exception as exc:
        jobs.append({"error": exc})


def _run_jobs(url: str, env: dict[str, Any], jobs: list[dict[str, Any]]) -> None:
    for who, params in LOAD_JOBS:
        t0 = time.monotonic()
        model_id = submit(url, env[who], env["volume"], params)
        jobs.append({"who": who, "params": params, "id": model_id, "submitted": t0})
    for job in jobs:
        model = wait_done(url, env["admin"], job["id"])
        job["done"] = time.monotonic()
        job["server_run_s"] = _seconds_between(model["started"], model["finished"])


def _seconds_between(a: str, b: str) -> float:
    from datetime import datetime

    return (datetime.fromisoformat(b) - datetime.fromisoformat(a)).total_seconds()


def drive(url: str, env: dict[str, Any], big: Path, cfg: dict[str, Any]) -> dict[str, Any]:
    """2 s in: the jobs; when they are done (at the latest halfway): the upload."""
    time.sleep(max(0.0, cfg["start"] + 2.0 - time.monotonic()))
    jobs: list[dict[str, Any]] = []
    thread = threading.Thread(target=run_jobs, args=(url, env, jobs))
    thread.start()
    backup = None
    if cfg.get("backup"):
        time.sleep(1.0)  # the jobs under way
        backup = take_backup(cfg["backup"])
    thread.join(timeout=max(0.0, (cfg["start"] + cfg["end"]) / 2 - time.monotonic()))
    t0 = time.monotonic()
    upload(url, env["ana"], big)
    uploaded = (t0, time.monotonic())
    thread.join()
    for job in jobs:
        if "error" in job:
            raise RuntimeError(f"a load job failed: {job['error']!r}") from job["error"]
    return {
        "jobs": jobs,
        "job_phase": (min(j["submitted"] for j in jobs), max(j["done"] for j in jobs)),
        "upload_phase": uploaded,
        "backup": backup,
    }


def take_backup(target: dict[str, Any]) -> dict[str, Any]:
    """``miss backup`` of the running server's folder and database; its figures."""
    env = {**os.environ, "MISS_DATA_DIR": target["data"]}
    if target["database"]:
        env["MISS_DATABASE_URL"] = target["database"]
    t0 = time.monotonic()
    cmd = [sys.executable, "-m", "miss.cli", "backup", target["dest"]]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    seconds = time.monotonic() - t0
    if done.returncode != 0:
        raise RuntimeError(f"miss backup failed: {done.stderr}")
    size = sum(p.stat().st_size for p in Path(target["dest"]).rglob("*") if p.is_file())
    return {"seconds": round(seconds, 2), "mb": round(size / 2**20, 1), "said": done.stdout}


def server_cpu(pid: int, processes: int = 1) -> float:
    """CPU seconds of the server process (its own threads, not the workers); with
    ``--processes N`` > 1, of its N server processes (the master's children) too."""
    total = _cpu(pid)
    if processes > 1:
        for child in Path(f"/proc/{pid}/task").glob("*/children"):
            total += sum(_cpu(int(c)) for c in child.read_text().split())
    return total


def _cpu(pid: int) -> float:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except FileNotFoundError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


# -- figures -------------------------------------------------------------------------------


def stats(kind: str, samples: list[tuple[float, bool]], seconds: float) -> dict[str, Any]:
    """requests, failures, req/s, p50/p99/max ms of (latency s, ok) pairs."""
    ms = sorted(1000 * s for s, _ in samples)
    return {
        "class": kind,
        "requests": len(ms),
        "failures": sum(not ok for _, ok in samples),
        "req_per_s": len(ms) / seconds if seconds > 0 else 0.0,
        "p50_ms": _quantile(ms, 0.50),
        "p99_ms": _quantile(ms, 0.99),
        "max_ms": ms[-1] if ms else float("nan"),
    }


def _quantile(sorted_ms: list[float], q: float) -> float:
    if not sorted_ms:
        return float("nan")
    if len(sorted_ms) == 1:
        return sorted_ms[0]
    return statistics.quantiles(sorted_ms, n=1000, method="inclusive")[round(q * 1000) - 1]


def within(t: float, phase: tuple[float, float]) -> bool:
    return phase[0] <= t <= phase[1]


def summarise(
    viewers: list[list[Any]], probes: list[list[Any]], driven: dict[str, Any], seconds: float
) -> list[dict[str, Any]]:
    rows = [
        stats(kind, [(s[2], s[3]) for s in viewers if s[0] == kind], seconds)
        for kind in VIEWER_CLASSES
    ]
    jobs, up = driven["job_phase"], driven["upload_phase"]
    fetches = [s for s in viewers if s[0] == "model fetch cached"]
    rows += [
        stats(
            f"model fetch cached, {phase}",
            [(s[2], s[3]) for s in fetches if pick(s[1])],
            seconds,
        )
        for phase, pick in (
            ("during jobs", lambda t: within(t, jobs)),
            ("during upload", lambda t: within(t, up)),
            ("viewers only", lambda t: not within(t, jobs) and not within(t, up)),
        )
    ]
    groups = {
        "probe during jobs": [(s, ok) for t, s, ok in probes if within(t, jobs)],
        "probe during upload": [(s, ok) for t, s, ok in probes if within(t, up)],
        "probe, viewers only": [
            (s, ok) for t, s, ok in probes if not within(t, jobs) and not within(t, up)
        ],
    }
    span = {
        "probe during jobs": jobs[1] - jobs[0],
        "probe during upload": up[1] - up[0],
        "probe, viewers only": probes[-1][0] - probes[0][0] - _union(jobs, up),
    }
    rows += [
        stats(kind, group, max(span[kind], PROBE_EVERY * len(group)))
        for kind, group in groups.items()
    ]
    return rows


def _union(a: tuple[float, float], b: tuple[float, float]) -> float:
    """Seconds covered by two intervals together."""
    overlap = max(0.0, min(a[1], b[1]) - max(a[0], b[0]))
    return (a[1] - a[0]) + (b[1] - b[0]) - overlap


def job_rows(driven: dict[str, Any], start: float) -> list[list[Any]]:
    return [
        [
            j["who"],
            json.dumps(j["params"]),
            round(j["submitted"] - start, 2),
            round(j["done"] - j["submitted"], 2),
            round(j["server_run_s"], 2),
        ]
        for j in driven["jobs"]
    ]


def report(rows: list[dict[str, Any]], jobs: list[list[Any]], context: dict[str, Any]) -> str:
    header = ["class", "requests", "failures", "req/s", "p50 ms", "p99 ms", "max ms"]
    table = markdown_table(
        header,
        [
            [
                r["class"],
                r["requests"],
                r["failures"],
                r["req_per_s"],
                r["p50_ms"],
                r["p99_ms"],
                r["max_ms"],
            ]
            for r in rows
        ],
    )
    job_table = markdown_table(
        ["account", "parameters", "submitted at s", "submit to done s", "worker run s"], jobs
    )
    return (
        f"{context['viewers']} viewers for {context['seconds']:g} s ({context['slices']} slice(s) "
        f"per loop, think {context['think']:g} s), "
        f"4 jobs ({context['workers']} job worker(s)), upload of {context['upload_mb']:.0f} MB during "
        f"{context['upload_s']:.1f} s. Load average before/after: {context['load_before']} / "
        f"{context['load_after']} on {os.cpu_count()} cores; the server process used "
        f"{context['server_cpu_s']:.1f} CPU s ({context['cpu_ms_per_request']:.1f} ms per "
        f"request, uploads and slice rendering included); the viewers' own process "
        f"{context['viewers_cpu_s']:.1f} CPU s.\n\n" + table + "\nJobs:\n\n" + job_table
    )


# -- main ----------------------------------------------------------------------------------


def upload_file() -> Path:
    from scaling import volume_file  # the CThead resampled, cached beside the others

    return volume_file(UPLOAD_SHAPE)


def measure(
    url: str,
    pid: int,
    env: dict[str, Any],
    args: argparse.Namespace,
    work: Path,
    processes: int = 1,
    backup: dict[str, Any] | None = None,
) -> dict:
    big = upload_file()
    cfg = {"url": url, "seconds": args.seconds, "think": args.think, "slices": args.slices}
    cfg["backup"] = backup
    cfg |= {k: env[k] for k in ("sessions", "models", "volume", "views")}
    ctx = mp.get_context("spawn")
    stop, ready = ctx.Event(), ctx.Barrier(3)
    viewers = ctx.Process(
        target=viewers_main, args=(cfg, ready, str(work / "viewers.json")), daemon=True
    )
    probe = ctx.Process(
        target=probe_main, args=(cfg, ready, stop, str(work / "probe.json")), daemon=True
    )
    load_before = [round(x, 2) for x in os.getloadavg()]
    viewers.start()
    probe.start()
    synced_start(cfg, ready)
    start = cfg["start"]
    cpu0 = server_cpu(pid, processes)
    try:
        driven = drive(url, env, big, cfg)
        viewers.join()
    finally:
        stop.set()
        probe.join()
    context = {
        "viewers": args.viewers,
        "seconds": args.seconds,
        "think": args.think,
        "slices": args.slices,
        "workers": args.workers,
        "upload_mb": big.stat().st_size / 2**20,
        "upload_s": driven["upload_phase"][1] - driven["upload_phase"][0],
        "load_before": load_before,
        "load_after": [round(x, 2) for x in os.getloadavg()],
        "server_cpu_s": server_cpu(pid, processes) - cpu0,
        "processes": processes,
        "backup": driven["backup"],
    }
    viewed = json.loads((work / "viewers.json").read_text())
    samples = viewed["samples"]
    context["viewers_cpu_s"] = viewed["cpu_s"]
    probes = json.loads((work / "probe.json").read_text())
    rows = summarise(samples, probes, driven, args.seconds)
    context["cpu_ms_per_request"] = 1000 * context["server_cpu_s"] / (len(samples) + len(probes))
    failed = [s for s in samples if not s[3]] + [p for p in probes if not p[2]]
    return {
        "rows": rows,
        "jobs": job_rows(driven, start),
        "context": context,
        "phases_s": {
            name: [round(t - start, 2) for t in driven[name]]
            for name in ("job_phase", "upload_phase")
        },
        "failed": [[s[0], round(s[1] - start, 2), *s[2:]] for s in failed[:20] if len(s) == 5],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=35.0, help="measured time (35)")
    parser.add_argument("--viewers", type=int, default=50, help="concurrent viewers (50)")
    parser.add_argument("--think", type=float, default=1.0, help="mean pause per loop, s (1)")
    parser.add_argument("--slices", type=int, default=1, help="slice images per loop (1)")
    parser.add_argument(
        "--workers",
        type=int,
        default=2,
        help="job workers in all, split between --processes (2; the server's default is 1)",
    )
    parser.add_argument("--database", choices=("sqlite", "postgres"), default="sqlite")
    parser.add_argument(
        "--processes", default="1", help="server processes, a run each: '1,2' (PostgreSQL)"
    )
    parser.add_argument(
        "--backup", action="store_true", help="miss backup during the jobs, restored, compared"
    )
    args = parser.parse_args(argv)
    counts = [int(n) for n in args.processes.split(",")]
    cluster = None
    if args.database == "postgres":
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
        from support import pg

        cluster = pg.Cluster()
    results, tables, problems = [], [], []
    try:
        for n in counts:
            result = one_run(args, n, cluster)
            results.append(result)
            problems += result.pop("problems", [])
            title = f"### {n} server process(es), {args.database}\n\n" if cluster else ""
            tables.append(title + report(result["rows"], result["jobs"], result["context"]))
    finally:
        if cluster is not None:
            cluster.stop()
    table = "\n".join(tables) + "".join(
        f"\n{r['backup_report']}" for r in results if r.get("backup_report")
    )
    print(table)
    name = "load" if args.database == "sqlite" else f"load_{args.database}"
    save(name, {"runs": results} if len(results) > 1 else results[0], table)
    failures = sum(r["failures"] for result in results for r in result["rows"])
    if failures:
        failed = [f for result in results for f in result["failed"]]
        print(f"{failures} request(s) failed, e.g. {failed[:5]}", file=sys.stderr)
    for problem in problems:
        print(problem, file=sys.stderr)
    return 1 if failures or problems else 0


def one_run(args: argparse.Namespace, processes: int, cluster: Any) -> dict[str, Any]:
    """Setup, the measured load and (``--backup``) the restored copy compared."""
    with tempfile.TemporaryDirectory(prefix="miss-load-") as tmp:
        work = Path(tmp)
        (work / "data").mkdir()
        database = cluster.create(f"load_{processes}") if cluster else ""
        # --workers is the jobs at once in all: split between the processes, so that 1
        # and 2 processes run the same jobs side by side.
        workers = max(1, args.workers // processes)
        proc, url = start_server(work / "data", workers, database, processes)
        target = None
        if args.backup:
            target = {"data": str(work / "data"), "database": database, "dest": str(work / "b")}
        try:
            env = setup(url, args.viewers)
            result = measure(url, proc.pid, env, args, work, processes, target)
        except BaseException:
            print((work / "server.log").read_text()[-4000:], file=sys.stderr)
            raise
        finally:
            stop_server(proc, timeout=60)
            # Kept for a look after the run (the data folder goes).
            shutil.copy(work / "server.log", Path(tempfile.gettempdir()) / "miss-load-server.log")
        if target is not None:
            restored = cluster.create(f"restored_{processes}") if cluster else ""
            result["problems"], result["backup_report"] = check_backup(
                work, database, restored, result["context"]["backup"]
            )
    return result


def check_backup(
    work: Path, database: str, restored: str, taken: dict[str, Any]
) -> tuple[list[str], str]:
    """Restore the backup into a fresh folder and database; compare with the source."""
    from miss.server.storage.backup import MANIFEST, restore

    source_url = database or f"sqlite:///{work / 'data' / 'miss.sqlite3'}"
    fresh = work / "restored"
    restored_url = restored or f"sqlite:///{fresh / 'miss.sqlite3'}"
    t0 = time.monotonic()
    restore(work / "b", fresh, restored_url)
    restore_s = time.monotonic() - t0
    manifest = json.loads((work / "b" / MANIFEST).read_text())
    before, after = all_rows(source_url), all_rows(restored_url)
    changed = {  # models whose row changed after the backup: the jobs under way
        key for key, row in after["models"].items() if before["models"].get(key) != row
    }
    # Every restored row is in the source, equal (rows made after the backup, like the
    # upload's volume, are only in the source).
    problems = []
    for table, rows in after.items():
        for key, row in rows.items():
            if table == "models" and key in changed:
                continue
            if before[table].get(key) != row:
                problems.append(f"restored {table} row {key} differs from the source")
    running = {key[0] for key in changed}
    files = 0
    for relative in manifest["files"]:
        if any(f"models/{m}/" in relative for m in running):
            continue
        files += 1
        if (fresh / relative).read_bytes() != (work / "data" / relative).read_bytes():
            problems.append(f"restored {relative} differs from the source")
    text = (
        f"Backup during the jobs: {taken['mb']} MB in {taken['seconds']} s; restored in "
        f"{restore_s:.1f} s; {sum(len(r) for r in after.values())} rows and {files} files "
        f"compared ({len(changed)} model row(s) of jobs running at the backup left out): "
        f"{len(problems)} difference(s).\n"
    )
    return problems[:20], text


def all_rows(url: str) -> dict[str, dict[Any, Any]]:
    """Every row of every table, by primary key."""
    from sqlalchemy import create_engine, text

    from miss.server.storage.db import Base

    engine = create_engine(url)
    out: dict[str, dict[Any, Any]] = {}
    try:
        with engine.connect() as conn:
            for table in Base.metadata.sorted_tables:
                key = [c.name for c in table.primary_key.columns]
                found = conn.execute(text(f"SELECT * FROM {table.name}")).mappings()
                out[table.name] = {
                    tuple(r[k] for k in key): json.dumps(dict(r), sort_keys=True, default=str)
                    for r in found
                }
    finally:
        engine.dispose()
    return out


if __name__ == "__main__":
    sys.exit(main())
