"""The same job through the server and through the command line (issue 41).

    .venv/bin/python benchmarks/server_vs_cli.py [--repeats 3] [--no-mr]

A real ``miss serve`` (temporary data folder, SQLite, one worker and its warm spare) gets
the CThead (256 x 256 x 113 NIfTI) and the MR head (512 x 512 x 120 DICOM, zipped); the
command line reads the same files. Each repeat, in turn:

- ``miss convert FILE -o model.glb --level L``, timed as a whole process from outside
  (imports included): what a radiologist waits for at a terminal;
- the same job posted to ``POST /api/models`` (after a pause that lets the next spare
  worker finish warming up, as between a physician's clicks), polled every 50 ms on one
  kept connection: **drawable**, when the model can be drawn (its GLB, or its levels of
  detail, listed on the row), and **free**, when the job is done and its worker free
  (preview, levels of detail and the internal form for the other formats included). The
  model is deleted after each repeat, so the next one is the same job again.

The job's own timeline (its ``stats.seconds``: read, preview, surface, decimate, measure,
levels of detail, write, keep) says where the server's time goes.

Writes ``results/server_vs_cli.{json,md}``; the targets: drawable within 1.1x the command's
whole process, free within 1.3x.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
from common import markdown_table, save
from first_pixels import cthead_file
from load import log_in, start_server, stop_server, upload
from volume_view import mr_zip

MR_DIR = Path(__file__).resolve().parents[2] / "shared/datasets/mr_head_dicom_vsseg001_t1"
#: (name, the file the server gets, the path the command reads, level)
CASES = [("CThead bone", cthead_file, cthead_file, 1500.0),
         ("MR head skin", mr_zip, lambda: MR_DIR, 270.0)]  # fmt: skip
PAUSE = 8.0  # seconds for the next spare worker to warm up between jobs
POLL = 0.05


def cli_seconds(path: Path, level: float, out: Path) -> float:
    """``miss convert`` as a whole process, from outside."""
    cmd = [str(Path(sys.executable).with_name("miss")), "convert", str(path),
           "-o", str(out / "model.glb"), "--level", f"{level:g}"]  # fmt: skip
    start = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True)
    return time.perf_counter() - start


def server_run(http: httpx.Client, volume: str, level: float) -> dict[str, Any]:
    """One job posted and followed: drawable and free seconds, and its stage seconds."""
    start = time.perf_counter()
    r = http.post("/api/models", json={"volume": volume, "level": level})
    assert r.status_code in (200, 202), r.text
    model_id = r.json()["id"]
    drawable = None
    while True:
        row = http.get(f"/api/models/{model_id}").json()
        now = time.perf_counter() - start
        if drawable is None and ((row.get("files") or {}).get("glb") or row.get("lod")):
            drawable = now
        if row["status"] in ("done", "failed"):
            assert row["status"] == "done", row.get("error")
            break
        time.sleep(POLL)
    stats = row.get("stats") or {}
    http.delete(f"/api/models/{model_id}").raise_for_status()  # the next repeat: the same job
    from datetime import datetime

    created, started, finished = (
        datetime.fromisoformat(row[k]) for k in ("created", "started", "finished")
    )
    return {"drawable": drawable if drawable is not None else now, "free": now,
            "stages": stats.get("seconds", {}), "triangles": stats.get("triangles"),
            "queued_s": (started - created).total_seconds(),
            "ran_s": (finished - started).total_seconds(),
            "ready_s": stats.get("ready_seconds")}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-mr", action="store_true", help="the CThead only")
    args = parser.parse_args(argv)
    cases = CASES[:1] if args.no_mr else CASES
    work = Path(tempfile.mkdtemp(prefix="server-vs-cli-"))
    (work / "data").mkdir()
    proc, url = start_server(work / "data", workers=1)
    results: list[dict[str, Any]] = []
    try:
        headers = log_in(url, "admin")
        with httpx.Client(base_url=url, headers=headers, timeout=900) as http:
            for name, upload_file, cli_path, level in cases:
                volume = upload(url, headers, upload_file())["id"]
                runs = []
                for _ in range(args.repeats):
                    cli = cli_seconds(cli_path(), level, work)
                    time.sleep(PAUSE)
                    runs.append({"cli": cli, **server_run(http, volume, level)})
                results.append({"case": name, "level": level, "runs": runs})
                print(name, runs[-1], flush=True)
    finally:
        stop_server(proc, timeout=60)
        shutil.rmtree(work, ignore_errors=True)
    text = table(results)
    print(text)
    save("server_vs_cli", {"cases": results}, text)
    return 0


def table(results: list[dict[str, Any]]) -> str:
    rows, stages = [], []
    for case in results:
        runs = case["runs"]
        cli = statistics.median(r["cli"] for r in runs)
        drawable = statistics.median(r["drawable"] for r in runs)
        free = statistics.median(r["free"] for r in runs)
        rows.append([case["case"], f"{cli:.2f}", f"{drawable:.2f}", f"{drawable / cli:.2f}x",
                     f"{free:.2f}", f"{free / cli:.2f}x", str(runs[-1]["triangles"])])  # fmt: skip
        names = [k for k in runs[-1]["stages"] if k != "total"]
        stages.append(f"{case['case']}: " + ", ".join(
            f"{k} {statistics.median(r['stages'].get(k, 0.0) for r in runs):.2f}" for k in names))  # fmt: skip
    head = ["case", "miss convert s", "server: drawable s", "vs convert",
            "server: free s", "vs convert", "triangles"]  # fmt: skip
    return (markdown_table(head, rows) + "\n\nThe server job's own seconds (medians):\n\n"
            + "\n".join(f"- {s}" for s in stages) + "\n")  # fmt: skip


if __name__ == "__main__":
    sys.exit(main())
