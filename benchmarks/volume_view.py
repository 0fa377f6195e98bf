"""Opening a model with its scan shown in 3-D (``/models/{id}?view=volume``) to the first
drawn volume, in chromium with software WebGL as CI has it.

    .venv/bin/python benchmarks/volume_view.py [--runs 5] [--mr]

A real ``miss serve`` (temporary data folder, SQLite) gets the CThead (256 x 256 x 113,
as NIfTI) and, with ``--mr``, the MR head (512 x 512 x 120 DICOM, zipped); each gets a
bone-level model. Each run opens a new tab of one browser profile kept on disk (its
cache as a returning user's: the first run, not counted, fills it; the voxels are then
answered from it, ``immutable``) and waits for the page to say the volume is drawn (the
viewer's fence after the frame: ``window.__miss.volume.drawnAt``, ms since the
navigation started): its first (fast) picture and the full one, and where the time went
before them (the voxels in the page, the layer built: ``performance`` marks). Also per
run: frames while turning (the camera turned 3 degrees about the target each, one after
another as a drag asks for them, the first WARM not counted: the fast frames size
themselves to the device), the fast frames' scale reached (of the canvas a side), the
full frame once the camera stops (median of SETTLED), the voxel bytes on the wire (level
0, gzip, measured once with an empty cache) against the stored int16 bytes, and the
page's JS heap.

Writes ``results/volume_view.{json,md}``.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import httpx
from common import CACHE, markdown_table, save
from first_pixels import CHROMIUM, CHROMIUM_ARGS, LAPTOP, cthead_file
from load import PASSWORD, log_in, start_server, stop_server, submit, upload, wait_done

MR = Path(__file__).resolve().parents[2] / "shared/datasets/mr_head_dicom_vsseg001_t1"
LEVELS = {"CThead": 1500.0, "MR head": 600.0}
TURNS = 10
WARM = 5
SETTLED = 3


def mr_zip() -> Path:
    """The MR head's DICOM series zipped in the benchmark cache (made once)."""
    path = CACHE / "mr_head_vsseg001.zip"
    if not path.is_file():
        CACHE.mkdir(parents=True, exist_ok=True)
        with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
            for f in sorted(MR.iterdir()):
                zf.write(f, f"series/{f.name}")
    return path


def prepare(url: str, headers: dict[str, str], name: str, path: Path) -> dict[str, Any]:
    """Upload a scan, build its bone model; the voxels' size on the wire, once."""
    volume = upload(url, headers, path)
    model = wait_done(url, headers, submit(url, headers, volume["id"], {"level": LEVELS[name]}))
    r = httpx.get(f"{url}/api/volumes/{volume['id']}/voxels", headers=headers, timeout=300)
    r.raise_for_status()
    dims = volume["dims"]
    return {
        "name": name,
        "model": model["id"],
        "dims": dims,
        "int16_bytes": 2 * dims[0] * dims[1] * dims[2],
        "wire_bytes": int(r.headers["content-length"]),
    }


def open_once(context: Any, model_id: str) -> dict[str, float]:
    """One tab: navigation start -> the volume drawn; frames while turning; JS heap."""
    page = context.new_page()
    page.set_default_timeout(120_000)
    try:
        page.goto(f"/models/{model_id}?view=volume")
        page.wait_for_function("() => window.__miss.volume && window.__miss.volume.on")
        volume = page.evaluate("() => window.__miss.volume")
        marks = page.evaluate(
            "() => Object.fromEntries(performance.getEntriesByType('mark')"
            ".map((m) => [m.name, m.startTime]))"
        )
        turns = page.evaluate(f"() => window.__miss.timeVolumeFrames({WARM + TURNS}, 0.05)")
        scale = page.evaluate("() => window.__miss.volumeFastScale")
        settled = [
            page.evaluate("() => window.__miss.timeSettledFrame(0.05)") for _ in range(SETTLED)
        ]
        heap = page.evaluate("() => performance.memory ? performance.memory.usedJSHeapSize : 0")
        return {
            "voxels_s": marks["volume:voxels"] / 1000,
            "layer_s": marks["volume:layer"] / 1000,
            "first_s": volume["firstAt"] / 1000,
            "drawn_s": volume["drawnAt"] / 1000,
            "turn_ms": statistics.median(turns[WARM:]),
            "fast_scale": scale,
            "settled_ms": statistics.median(settled),
            "heap_mb": heap / 2**20,
        }
    finally:
        page.close()


def measure(url: str, scans: list[dict[str, Any]], runs: int, profile: Path) -> None:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        context = p.chromium.launch_persistent_context(
            str(profile), executable_path=CHROMIUM, args=CHROMIUM_ARGS, viewport=LAPTOP,
            base_url=url,
        )  # fmt: skip
        try:
            r = context.request.post(
                "/api/auth/login", data={"username": "admin", "password": PASSWORD}
            )
            assert r.status == 200, r.text()
            for scan in scans:
                open_once(context, scan["model"])  # fills the cache; not counted
                scan["runs"] = [open_once(context, scan["model"]) for _ in range(runs)]
                shot = context.new_page()
                shot.goto(f"/models/{scan['model']}?view=volume")
                shot.wait_for_function("() => window.__miss.volume && window.__miss.volume.on")
                slug = scan["name"].lower().replace(" ", "-")
                shot.locator("#stage canvas").screenshot(path=f"/tmp/volume-view-{slug}.png")
                shot.close()
        finally:
            context.close()


def table(scans: list[dict[str, Any]]) -> str:
    rows = []
    for s in scans:
        med = {k: statistics.median(r[k] for r in s["runs"]) for k in s["runs"][0]}
        rows.append([
            s["name"], "x".join(map(str, s["dims"])), round(s["wire_bytes"] / 2**20, 2),
            round(s["wire_bytes"] / s["int16_bytes"], 3), round(med["voxels_s"], 2),
            round(med["layer_s"], 2), round(med["first_s"], 2), round(med["drawn_s"], 2),
            round(med["turn_ms"]), round(med["fast_scale"], 3), round(med["settled_ms"]),
            round(med["heap_mb"], 1), len(s["runs"]),
        ])  # fmt: skip
    header = ["scan", "dims", "voxels sent MB", "x int16", "voxels in s", "layer s",
              "open -> first picture s", "open -> full picture s", "frame turning ms",
              "fast scale", "full frame ms", "JS heap MB", "runs"]  # fmt: skip
    return markdown_table(header, rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--mr", action="store_true", help="also the 512x512x120 MR head")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="volume-view-"))
    (work / "data").mkdir()
    proc, url = start_server(work / "data", workers=1)
    try:
        headers = log_in(url, "admin")
        scans = [prepare(url, headers, "CThead", cthead_file())]
        if args.mr:
            scans.append(prepare(url, headers, "MR head", mr_zip()))
        measure(url, scans, args.runs, work / "profile")
    finally:
        stop_server(proc)
        shutil.rmtree(work, ignore_errors=True)
    text = table(scans)
    print(text)
    save("volume_view", {"scans": scans}, text + "\n")


if __name__ == "__main__":
    main()
