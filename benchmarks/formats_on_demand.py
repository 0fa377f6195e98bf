"""Formats when asked (issue 41): a model's disk right after its job, against writing every
format at once as before, and what each format's first and second download costs.

    nice -n 19 .venv/bin/python benchmarks/formats_on_demand.py [--cases cthead,mrhead]

A real ``miss serve`` (a temporary data folder, SQLite, one job worker) gets each volume
(uploaded as NIfTI) and runs the default job at its level: CThead bone at 1500, the MR head
(``mr_head_dicom_vsseg001_t1``, 512 x 512 x 120) skin at 270. Then:

- disk: the model's folder (its worker's log left out) right after the job; "all formats
  at once": that folder without the internal form, plus every other format as the writers
  make it from the same scene in this process (what a job wrote before); and the folder
  after one download of every format;
- each format's first download (made on the server, then sent) and second (a file read):
  seconds from the request to its first byte and to its last, over HTTP on this machine;
- every download is checked byte for byte against the writers' output in this process.

Writes ``results/formats_on_demand.{json,md}``.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
from common import CACHE, markdown_table, save, write_nifti
from load import log_in, start_server, stop_server, submit, upload, wait_done

from miss.export import export
from miss.server.storage import formats

DATASETS = Path(__file__).resolve().parents[2] / "shared/datasets"
#: name: (source, NIfTI in the cache, the job's parameters)
CASES = {
    "cthead": (
        DATASETS / "ct_head_stanford_cthead/CThead.nhdr",
        "cthead_256x256x113.nii",
        {"level": 1500},
    ),
    "mrhead": (
        DATASETS / "mr_head_dicom_vsseg001_t1",
        "mr_head_vsseg001_512x512x120.nii",
        {"level": 270},
    ),
}
MB = 2**20


def volume_file(name: str) -> Path:
    """The case's volume as an uncompressed NIfTI in the benchmark cache (made once)."""
    source, cached, _ = CASES[name]
    path = CACHE / cached
    if not path.is_file():
        from miss.io import load_volume

        path.parent.mkdir(parents=True, exist_ok=True)
        write_nifti(load_volume(source), path)
    return path


def folder_bytes(folder: Path, skip: tuple[str, ...] = ("worker.log",)) -> int:
    """Bytes under ``folder`` but the names in ``skip`` at its top."""
    return sum(
        p.stat().st_size
        for p in folder.rglob("*")
        if p.is_file() and p.relative_to(folder).parts[0] not in skip
    )


def timed_get(url: str, headers: dict[str, str]) -> tuple[float, float, bytes]:
    """Seconds to the first byte and to the last of a GET, and the bytes."""
    start = time.perf_counter()
    first, chunks = None, []
    with httpx.stream("GET", url, headers=headers, timeout=900) as r:
        r.raise_for_status()
        for chunk in r.iter_raw():
            first = first or time.perf_counter() - start
            chunks.append(chunk)
    return first or 0.0, time.perf_counter() - start, b"".join(chunks)


def one_case(name: str, work: Path) -> dict[str, Any]:
    """Run the case's job on a fresh server, then download every format twice."""
    data = work / name / "data"
    data.mkdir(parents=True)
    proc, url = start_server(data, workers=1)
    try:
        headers = log_in(url, "admin")
        volume = upload(url, headers, volume_file(name))["id"]
        start = time.perf_counter()
        model = wait_done(url, headers, submit(url, headers, volume, CASES[name][2]), 1800)
        job_seconds = time.perf_counter() - start
        folder = data / "models" / model["id"]
        before = folder_bytes(folder)
        stored = formats.read_scene(folder / formats.MESH_FILE)
        rows, old = [], before - (folder / formats.MESH_FILE).stat().st_size
        for fmt in formats.ON_REQUEST:
            t0 = time.perf_counter()
            want = export(stored.scene, fmt, title=stored.title, metadata=stored.metadata)
            write_seconds = time.perf_counter() - t0
            old += len(want)
            link = f"{url}/api/models/{model['id']}/model.{fmt}"
            first = timed_get(link, headers)
            second = timed_get(link, headers)
            same = hashlib.sha256(first[2]).digest() == hashlib.sha256(want).digest()
            assert same and second[2] == first[2], f"{name} {fmt}: not the writers' bytes"
            rows.append({"format": fmt, "bytes": len(want), "in_process_write_s": write_seconds,
                         "first_ttfb_s": first[0], "first_last_s": first[1],
                         "second_ttfb_s": second[0], "second_last_s": second[1]})  # fmt: skip
        return {
            "case": name, "params": CASES[name][2], "model": model["id"],
            "triangles": model["stats"]["triangles"], "glb_bytes": model["files"]["glb"]["bytes"],
            "job_seconds": job_seconds, "job_stage_seconds": model["stats"]["seconds"],
            "bytes_after_job": before, "bytes_all_formats_at_once": old,
            "bytes_after_every_download": folder_bytes(folder), "downloads": rows,
        }  # fmt: skip
    finally:
        stop_server(proc, timeout=20)


def tables(results: list[dict[str, Any]]) -> str:
    disk = [
        [r["case"], r["triangles"], r["glb_bytes"] / MB, r["bytes_after_job"] / MB,
         r["bytes_after_job"] / r["glb_bytes"], r["bytes_all_formats_at_once"] / MB,
         r["bytes_after_every_download"] / MB, r["job_stage_seconds"].get("write", 0.0)]
        for r in results
    ]  # fmt: skip
    text = markdown_table(
        ["case", "triangles", "GLB MB", "after the job MB", "× GLB", "all formats at once MB",
         "after every download MB", "job's write s"],
        disk,
    )  # fmt: skip
    downloads = [
        [r["case"], d["format"], d["bytes"] / MB, d["in_process_write_s"], d["first_ttfb_s"],
         d["first_last_s"], d["second_ttfb_s"], d["second_last_s"]]
        for r in results
        for d in r["downloads"]
    ]  # fmt: skip
    return (
        text
        + "\n"
        + markdown_table(
            [
                "case",
                "format",
                "MB",
                "writer in process s",
                "1st: first byte s",
                "1st: last byte s",
                "2nd: first byte s",
                "2nd: last byte s",
            ],
            downloads,
        )  # fmt: skip
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--cases", default="cthead,mrhead", help="comma-separated: " + ",".join(CASES)
    )
    args = parser.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="miss-formats-"))
    try:
        results = [one_case(name, work) for name in args.cases.split(",")]
    finally:
        shutil.rmtree(work, ignore_errors=True)
    table = tables(results)
    print(table)
    save("formats_on_demand", {"cpus": os.cpu_count(), "results": results}, table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
