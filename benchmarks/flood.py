"""One account floods the server, another works: the worker's medians, quiet and flooded.

    .venv/bin/python benchmarks/flood.py [--repeats 5] [--workers 2] [--no-pacs]

A real ``miss serve`` on a free loopback port, a temporary data folder, the settings as
shipped (rates, slots, limits and quotas at their defaults) but ``--workers``. Two
ordinary accounts: ``ana`` (the colleague whose work is measured) and ``flood`` (the one
account that tries to take the server). With Orthanc installed (``make test`` installs
it), a real Orthanc holds a small CT series that both may import.

``ana``'s work, each ``--repeats`` times, quiet first, then while ``flood`` floods:

- a small job (CThead, 256 x 256 x 113, sample rate 2, a new level each time): from
  ``POST /api/models`` to ``done``;
- an upload (a 64 x 64 x 64 NIfTI): the whole ``POST /api/volumes``;
- 10 slice PNGs of her volume, each a slice not asked for before (cold);
- a PACS import of a 12-slice series, from the request to ``done``.

``flood``'s flood, all at once, for as long as ``ana`` is measured:

- jobs: keeps as many of the heaviest kind queued as it may (16 levels, split
  components, smoothing 500, schroeder at 0.0001), posting again whenever one is
  refused or ends;
- uploads: 4 connections that each send a multipart header and then one byte every 2 s;
- event streams: 20 at once on its own models;
- PACS imports: 40 posted in a burst, again as they are refused or end.

The flood runs in a process of its own, as another machine's client would: in ``ana``'s
process its 25 threads had held her requests behind the GIL. On this 2-core machine it
runs at ``--flood-nice`` (19 by default): its own client's CPU (about a core, parsing
answers) stands for other machines' and is kept off the server's cores as far as the
scheduler allows; ``--flood-nice 0`` gives it the same share as the server.
``ana``'s client is another machine's browser too: one client with its connections kept,
at ``--client-nice`` (19 by default) once the server and Orthanc run.

Writes ``results/flood.{json,md}``; the table gives each median quiet, flooded, and their
ratio (the target: within 2x).
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import socket
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from common import markdown_table, paper_volume_file, save, write_nifti
from load import PASSWORD, log_in, start_server, upload

from miss.server.core.settings import Settings
from miss.types import Volume


def heavy_job(n: int) -> dict[str, Any]:
    """The issue's heaviest job (16 levels, split components, smoothing 500, schroeder at
    0.0001), its levels moved by ``n`` so that each is a new model."""
    parts = [
        {"level": 200.0 + 100.0 * i + n, "components": "split", "smooth": 500} for i in range(16)
    ]
    return {"parts": parts, "decimate": "schroeder", "error_bound": 0.0001}


TIMEOUT = 900.0
TESTS = Path(__file__).resolve().parents[1] / "tests"


def small_volume(folder: Path) -> Path:
    """A 64^3 CT-like volume: a bright ball in air, 1 mm voxels (1 MB as NIfTI)."""
    grid = np.indices((64, 64, 64)).astype(np.float32) - 31.5
    data = np.where((grid**2).sum(axis=0) < 20.0**2, 1200, -1000).astype(np.int16)
    return write_nifti(Volume(data, np.eye(4)), folder / "ball.nii")


def wait_status(http: httpx.Client, path: str) -> dict[str, Any]:
    deadline = time.monotonic() + TIMEOUT
    while time.monotonic() < deadline:
        row = http.get(path).json()
        if row["status"] in ("done", "failed"):
            return row
        time.sleep(0.1)
    raise RuntimeError(f"{path} not done after {TIMEOUT} s")


class Ana:
    """The colleague: her volume, her repeats; each method returns seconds. One client
    with its connections kept, as her browser has (a new ``httpx`` client a request had
    cost 18 ms of this machine's CPU each, ten times a second while she waited)."""

    def __init__(self, url: str, headers: dict[str, str], volume: dict[str, Any], folder: Path):
        self.url, self.headers, self.volume, self.folder = url, headers, volume, folder
        self.http = httpx.Client(base_url=url, headers=headers, timeout=TIMEOUT)
        self.level, self.slice = 300.0, 0

    def job(self) -> float:
        self.level += 7.0
        start = time.monotonic()
        body = {"volume": self.volume["id"], "level": self.level, "sample_rate": 2,
                "decimate": "quadric"}  # fmt: skip
        r = self.http.post("/api/models", json=body)
        assert r.status_code in (200, 202), r.text
        row = wait_status(self.http, f"/api/models/{r.json()['id']}")
        assert row["status"] == "done", row
        return time.monotonic() - start

    def upload(self) -> float:
        path = small_volume(self.folder)
        start = time.monotonic()
        with open(path, "rb") as f:
            r = self.http.post("/api/volumes", files={"file": (path.name, f)})
        assert r.status_code == 201, r.text
        return time.monotonic() - start

    def slices(self) -> float:
        count = self.volume["views"]["axial"]["count"]
        start = time.monotonic()
        for _ in range(10):
            self.slice = (self.slice + 7) % count
            r = self.http.get(f"/api/volumes/{self.volume['id']}/slices/axial/{self.slice}.png")
            assert r.status_code == 200, r.text
        return (time.monotonic() - start) / 10

    def pacs(self, series: dict[str, str]) -> float:
        start = time.monotonic()
        r = self.http.post("/api/pacs/import", json=series)
        assert r.status_code == 202, r.text
        row = wait_status(self.http, f"/api/pacs/imports/{r.json()['id']}")
        assert row["status"] == "done", row
        return time.monotonic() - start


class Flood:
    """The flooding account's threads; ``counts`` says what the server answered them."""

    def __init__(self, url: str, headers: dict[str, str], volume: str, series: Any) -> None:
        self.url, self.headers, self.volume, self.series = url, headers, volume, series
        self.stop = threading.Event()
        self.counts: dict[str, int] = {}
        self.threads = [threading.Thread(target=self.jobs, daemon=True)]
        self.threads += [threading.Thread(target=self.trickle, daemon=True) for _ in range(4)]
        self.threads += [threading.Thread(target=self.stream, daemon=True) for _ in range(20)]
        if series:
            self.threads.append(threading.Thread(target=self.imports, daemon=True))

    def count(self, what: str, status: int | str) -> None:
        key = f"{what} {status}"
        self.counts[key] = self.counts.get(key, 0) + 1

    def jobs(self) -> None:
        with httpx.Client(base_url=self.url, headers=self.headers, timeout=TIMEOUT) as http:
            n = 0
            while not self.stop.is_set():
                n += 1  # a new job each time: the same parameters again are the same model
                r = http.post("/api/models", json={"volume": self.volume, **heavy_job(n)})
                self.count("job", r.status_code)
                self.stop.wait(0.5)

    def trickle(self) -> None:
        host, port = self.url.removeprefix("http://").split(":")
        while not self.stop.is_set():
            try:
                with socket.create_connection((host, int(port)), timeout=30) as s:
                    head = (
                        f"POST /api/volumes HTTP/1.1\r\nHost: {host}\r\n"
                        f"Authorization: {self.headers['Authorization']}\r\n"
                        "Content-Type: multipart/form-data; boundary=b\r\n"
                        "Content-Length: 10000000\r\n\r\n--b\r\n"
                        'Content-Disposition: form-data; name="file"; filename="x.nii"\r\n\r\n'
                    )
                    s.sendall(head.encode())
                    while not self.stop.wait(2.0):
                        s.sendall(b"\0")
            except OSError as e:
                self.count("trickle", type(e).__name__)
                self.stop.wait(1.0)

    def stream(self) -> None:
        with httpx.Client(base_url=self.url, headers=self.headers, timeout=TIMEOUT) as http:
            while not self.stop.is_set():
                models = http.get("/api/models").json()
                if not isinstance(models, list) or not models:  # refused (429), or none yet
                    self.stop.wait(1.0)
                    continue
                try:
                    with http.stream("GET", f"/api/models/{models[0]['id']}/events") as r:
                        self.count("events", r.status_code)
                        for _ in r.iter_bytes():
                            if self.stop.is_set():
                                return
                except httpx.HTTPError as e:
                    self.count("events", type(e).__name__)
                self.stop.wait(1.0)

    def imports(self) -> None:
        with httpx.Client(base_url=self.url, headers=self.headers, timeout=TIMEOUT) as http:
            while not self.stop.is_set():
                for _ in range(40):
                    self.count(
                        "import", http.post("/api/pacs/import", json=self.series).status_code
                    )
                self.stop.wait(2.0)

    def __enter__(self) -> Flood:
        for t in self.threads:
            t.start()
        time.sleep(5.0)  # the flood is in place before the first measurement
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        time.sleep(2.0)  # the API's own rate limit refills after the flood's requests
        models = httpx.get(self.url + "/api/models", headers=self.headers, timeout=TIMEOUT).json()
        for model in models if isinstance(models, list) else []:
            reason = (model.get("error") or "")[:60]
            self.count("job ended", f"{model['status']} {reason}".strip())


def _flood_process(args: tuple[Any, ...], nice: int, started: Any, stop: Any, out: Any) -> None:
    os.nice(nice)
    with Flood(*args) as flood:
        started.set()
        stop.wait()
    out.put(flood.counts)


@contextmanager
def flooding(*args: Any, nice: int) -> Iterator[dict[str, int]]:
    """``Flood(*args)`` in a process of its own at ``nice``, for the ``with`` block; the
    dict yielded holds what the server answered it once the block ends."""
    ctx = multiprocessing.get_context("spawn")
    started, stop, out = ctx.Event(), ctx.Event(), ctx.Queue()
    proc = ctx.Process(target=_flood_process, args=(args, nice, started, stop, out))
    proc.start()
    counts: dict[str, int] = {}
    try:
        if not started.wait(120):
            raise RuntimeError("the flood did not start in 120 s")
        yield counts
    finally:
        stop.set()
        counts.update(out.get(timeout=120))
        proc.join(30)


def pacs_series(stack: ExitStack, folder: Path) -> tuple[dict[str, str] | None, dict[str, str]]:
    """A small CT series in a real Orthanc, and the settings that point MISS at it."""
    sys.path.insert(0, str(TESTS))
    from pacs import orthanc
    from pacs.conftest import stow
    from pacs.dicom_data import write_ct_series

    if orthanc.available():
        print(f"no PACS part: {orthanc.available()}")
        return None, {}
    server = orthanc.start(folder / "orthanc")
    stack.callback(server.stop)
    import pydicom

    datasets = [pydicom.dcmread(p) for p in write_ct_series(folder / "series")]
    stow(server, datasets)
    first = datasets[0]
    series = {"study": str(first.StudyInstanceUID), "series": str(first.SeriesInstanceUID)}
    return series, server.env()


def accounts(url: str) -> dict[str, dict[str, str]]:
    admin = log_in(url, "admin")
    for name in ("ana", "flood"):
        body = {"name": name, "password": PASSWORD, "pacs": True}
        httpx.post(url + "/api/users", json=body, headers=admin, timeout=TIMEOUT).raise_for_status()
    return {name: log_in(url, name) for name in ("ana", "flood")}


def measure(ana: Ana, series: dict[str, str] | None, repeats: int) -> dict[str, list[float]]:
    runs: dict[str, list[float]] = {"small job": [], "upload": [], "slice": []}
    if series:
        runs["PACS import"] = []
    for _ in range(repeats):
        runs["small job"].append(ana.job())
        runs["upload"].append(ana.upload())
        runs["slice"].append(ana.slices())
        if series:
            runs["PACS import"].append(ana.pacs(series))
    return runs


def run(args: argparse.Namespace) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="miss-flood-") as tmp, ExitStack() as stack:
        folder = Path(args.keep or tmp)
        folder.mkdir(parents=True, exist_ok=True)
        series, pacs_env = (None, {}) if args.no_pacs else pacs_series(stack, folder)
        shipped = {
            "MISS_API_RATE": str(Settings.api_rate),
            "MISS_API_BURST": str(Settings.api_burst),
        }
        if args.job_cpu_seconds:
            shipped["MISS_JOB_CPU_SECONDS"] = f"{args.job_cpu_seconds:g}"
        proc, url = start_server(folder / "data", args.workers, env={**pacs_env, **shipped})
        stack.callback(proc.kill)
        who = accounts(url)
        ana = Ana(url, who["ana"], upload(url, who["ana"], paper_volume_file()), folder)
        flood_volume = upload(url, who["flood"], paper_volume_file())["id"]
        # Her client stands for her browser on another machine, as the flood's does.
        os.nice(args.client_nice)  # this thread's (Linux): not the server's nor Orthanc's
        quiet = measure(ana, series, args.repeats)
        with flooding(url, who["flood"], flood_volume, series, nice=args.flood_nice) as counts:
            flooded = measure(ana, series, args.repeats)
        return {"quiet": quiet, "flooded": flooded, "flood_answers": counts,
                "workers": args.workers, "repeats": args.repeats, "flood_nice": args.flood_nice,
                "client_nice": args.client_nice,
                "job_cpu_seconds": args.job_cpu_seconds or Settings.job_cpu_seconds}  # fmt: skip


def table(result: dict[str, Any]) -> str:
    rows = []
    for what, quiet in result["quiet"].items():
        q, f = statistics.median(quiet), statistics.median(result["flooded"][what])
        rows.append([what, f"{q:.3f}", f"{f:.3f}", f"{f / q:.2f}x", "yes" if f <= 2 * q else "no"])
    head = ["ana's", "quiet median s", "flooded median s", "ratio", "within 2x"]
    answers = ", ".join(f"{k}: {v}" for k, v in sorted(result["flood_answers"].items()))
    nice = result.get("flood_nice", 0)
    return (
        f"{markdown_table(head, rows)}\n\nThe flooding client at nice {nice}, ana's at nice "
        f"{result.get('client_nice', 0)}; "
        f"what it was answered: {answers}\n"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--no-pacs", action="store_true", help="leave the PACS part out")
    parser.add_argument("--keep", type=Path, help="a new folder for the run's data, kept")
    parser.add_argument(
        "--job-cpu-seconds", type=float, default=0.0,
        help="MISS_JOB_CPU_SECONDS for the run (0: as shipped): the longest a flood job holds a worker",
    )  # fmt: skip
    parser.add_argument(
        "--flood-nice", type=int, default=19,
        help="the flooding client's nice value (19: it stands for other machines)",
    )  # fmt: skip
    parser.add_argument(
        "--client-nice", type=int, default=19,
        help="ana's client's nice value once the servers run (19: her browser is elsewhere)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    result = run(args)
    text = table(result)
    print(text)
    save("flood", result, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
