"""Generate -> pixels, as a radiologist meets it: chromium clicks Generate on the volume page
and the benchmark waits for the model's pixels on the viewer's canvas.

    .venv/bin/python benchmarks/first_pixels.py [--runs 5] [--baseline OTHER/src]

A real ``miss serve`` (a temporary data folder, SQLite, the default job workers) gets the
CThead (256 x 256 x 113, uploaded as NIfTI); each run sets another level near the bone (so
no earlier model is reused), clicks Generate and watches the canvas. Nothing in MISS's
pages is asked when pixels change: a script put in every page before MISS's own makes the
WebGL canvas keep its drawing buffer and, after each frame the page drew, reads its middle
quarter once the GPU has finished that frame (a fence, looked at every 2 ms); a frame
counts as drawn when over 0.5 % of those pixels (every second one of every second row)
differ from the background colour the viewer says it clears to, at the time the fence was
seen passed. Until 2026-11-27 the probe read the canvas in every animation frame at once,
which made the page wait for the software renderer: up to 0.3 s of its start, a user's
page does not wait so. The click's time is the event's own timestamp, kept across the
move to the viewer page.

- first pixels: click -> the first frame with the model (a preview or the model) on it;
- full model: click -> the first frame drawn after the full model was put in the scene
  (the page says which one it drew in ``window.__miss.drawn``; a page that draws no
  preview draws the full model first);
- job: the seconds the job itself computed before the full model's GLB existed (read,
  preview, surface, decimation, GLB), from the model's stats; "full - job" is what the
  waiting, the page and the browser add (the median of each run's own difference);
- held: the seconds the job waited, its GLB in place, for the page to say it had drawn
  the model (``miss.server.jobs.turn``; 0 for a server that does not wait); done: the
  job's whole time from submission to done, which that wait lengthens;
- turn: once the job is done, a drag on the model (the mouse moved 40 px with its button
  down) -> the first frame with the turned model, the median of 5 drags: what a physician
  waits for at each step of turning it.

Runs are 5 s apart after each job is done. Every run is a new tab of one browser profile
kept on disk for the whole benchmark, as a user's browser: its cache and the code it
compiled stay between runs. The first round is not counted (it fills that cache, as a
user's earlier visits have). Until 2026-11-27 each run had a new browser context, whose
cache starts empty: every run was a first visit, whatever this said.

``--baseline SRC`` starts a second server from another source tree (``PYTHONPATH=SRC``, e.g.
a ``git worktree`` of an older commit) and alternates runs between the two, so both meet
the same noise. Writes ``results/first_pixels.{json,md}``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx
from common import CACHE, markdown_table, save, write_nifti
from load import PASSWORD, log_in, start_server, stop_server, upload

DATASETS = Path(
    os.environ.get("MISS_DATASETS", Path(__file__).resolve().parents[2] / "shared/datasets")
)
CTHEAD = DATASETS / "ct_head_stanford_cthead" / "CThead.nhdr"
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
LAPTOP = {"width": 1366, "height": 768}
#: Levels near the bone of the CThead's raw values (0..3272), one a run.
BONE = 1500
#: Share of the probed pixels that must differ from the background for a frame to count.
DRAWN = 0.005
#: Seconds between one run's finished job and the next click, as a physician looks at a
#: model before asking for another (a server's spare worker warms up meanwhile).
LOOK = 5.0
#: Drags measured on each run's finished model.
TURNS = 5

#: Put in every page before its own scripts: keeps WebGL's drawing buffer and reads the
#: middle of the canvas (a quarter of its pixels) once the GPU has finished a frame the
#: page drew; records the click on Generate.
PROBE = """
(() => {
  document.addEventListener('click', (e) => {
    if (e.target.closest && e.target.closest('#generate'))
      sessionStorage.setItem('clickAt', String(performance.timeOrigin + e.timeStamp));
  }, true);
  // A drag on the model (turning it): the last move's time.
  document.addEventListener('pointermove', (e) => {
    if (e.buttons) window.__turnAt = performance.timeOrigin + e.timeStamp;
  }, true);
  const getContext = HTMLCanvasElement.prototype.getContext;
  HTMLCanvasElement.prototype.getContext = function (type, attrs) {
    const gl = type === 'webgl2' || type === 'webgl';
    const ctx = getContext.call(this, type, gl ? { ...(attrs || {}), preserveDrawingBuffer: true } : attrs);
    if (gl && ctx && !contexts.some(([, c]) => c === ctx)) {
      contexts.push([this, ctx]);
      // The probe reads the canvas only in a frame after the page drew (cleared or drew
      // triangles): reading a software-rendered canvas each frame took the page's own time.
      for (const name of ['clear', 'drawElements', 'drawArrays', 'drawElementsInstanced', 'drawArraysInstanced']) {
        const own = ctx[name];
        if (own) ctx[name] = function (...args) { dirty.add(ctx); return own.apply(this, args); };
      }
    }
    if (gl && ctx && !window.__probe) watch();
    return ctx;
  };
  // Every WebGL context the page makes; the one read is the first whose canvas is in the
  // page (the viewer's: a page may make others off the page, e.g. to ask what draws).
  const contexts = [];
  const dirty = new Set();
  function watch() {
    const probe = window.__probe = { frames: [] };
    let last = -1, buffer = null, cleared = false, waiting = null;
    const now = () => performance.timeOrigin + performance.now();
    // After a frame the page drew: a fence, looked at every 2 ms without blocking the page
    // (a readPixels at once made the page wait for the software renderer, which a user's
    // page does not: up to 0.2 s of its start); once the GPU is past it, the pixels are read.
    const tick = () => {
      const found = contexts.find(([canvas, ctx]) => canvas.isConnected && !ctx.isContextLost());
      if (found && !waiting && dirty.has(found[1])) {
        const gl = found[1];
        dirty.delete(gl);
        if (gl.fenceSync) {
          waiting = [gl.fenceSync(gl.SYNC_GPU_COMMANDS_COMPLETE, 0), gl];
          gl.flush();
          setTimeout(look, 2);
        } else read(gl, now());
      }
      requestAnimationFrame(tick);
    };
    const look = () => {
      const [sync, gl] = waiting;
      if (!gl.isContextLost() && gl.getSyncParameter(sync, gl.SYNC_STATUS) !== gl.SIGNALED) {
        setTimeout(look, 2);
        return;
      }
      const t = now();
      if (!gl.isContextLost()) gl.deleteSync(sync);
      waiting = null;
      if (!gl.isContextLost()) read(gl, t);
    };
    const read = (gl, t) => {
      const w = gl.drawingBufferWidth, h = gl.drawingBufferHeight;
      const x = w >> 2, y = h >> 2, pw = w >> 1, ph = h >> 1;
      if (pw <= 0 || ph <= 0) return;
      if (!buffer || buffer.length !== pw * ph * 4) buffer = new Uint8Array(pw * ph * 4);
      gl.readPixels(x, y, pw, ph, gl.RGBA, gl.UNSIGNED_BYTE, buffer);
      // The viewer's clear colour, as it says (before it first draws: nothing counts).
      const hex = (window.__miss || {}).backgroundColor;
      if (!hex) { dirty.add(gl); return; }
      const r = parseInt(hex.slice(1, 3), 16), g = parseInt(hex.slice(3, 5), 16),
            b = parseInt(hex.slice(5, 7), 16);
      // Nothing counts before the viewer has cleared the canvas once (a corner shows it),
      // nor a buffer just resized and not drawn yet (transparent: the viewer draws opaque).
      if (!cleared) cleared = Math.abs(buffer[0] - r) + Math.abs(buffer[1] - g) + Math.abs(buffer[2] - b) <= 24;
      if (!cleared || buffer[3] === 0) { dirty.add(gl); return; }
      // Every second pixel of every second row: a quarter of them, the same share
      let other = 0, sum = 0, seen = 0;
      for (let row = 0; row < ph; row += 2) {
        for (let i = row * pw * 4; i < (row + 1) * pw * 4; i += 8) {
          const d = Math.abs(buffer[i] - r) + Math.abs(buffer[i + 1] - g) + Math.abs(buffer[i + 2] - b);
          if (d > 24) other++;
          seen++;
          sum = (sum + buffer[i] * 3 + buffer[i + 1] * 5 + buffer[i + 2] * 7) % 1000000007;
        }
      }
      if (sum !== last) {
        last = sum;
        const miss = window.__miss || {};
        probe.frames.push({ t, share: other / seen, drawn: miss.drawn || null });
      }
    };
    requestAnimationFrame(tick);
  }
})();
"""


def cthead_file() -> Path:
    """CThead as an uncompressed NIfTI in the benchmark cache (made once)."""
    path = CACHE / "cthead_256x256x113.nii"
    if not path.is_file():
        from miss.io import load_volume

        write_nifti(load_volume(CTHEAD), path)
    return path


class Target:
    """One running server (this tree's, or a baseline's) with the CThead uploaded."""

    def __init__(self, name: str, src: Path | None, work: Path) -> None:
        self.name = name
        data = work / name / "data"
        data.mkdir(parents=True)
        env = dict(os.environ)
        if src is not None:
            env["PYTHONPATH"] = str(src)
        old = dict(os.environ)
        os.environ.clear()
        os.environ.update(env)
        try:
            self.proc, self.url = start_server(data, workers=1)
        finally:
            os.environ.clear()
            os.environ.update(old)
        self.headers = log_in(self.url, "admin")
        self.volume = upload(self.url, self.headers, cthead_file())["id"]
        self.runs: list[dict[str, Any]] = []

    def stop(self) -> None:
        stop_server(self.proc, timeout=20)

    def model(self, model_id: str) -> dict[str, Any]:
        r = httpx.get(f"{self.url}/api/models/{model_id}", headers=self.headers, timeout=30)
        r.raise_for_status()
        return r.json()


def one_run(browser: Any, target: Target, level: int) -> dict[str, Any]:
    """Click Generate at ``level``; click -> first pixels and -> full model, seconds.
    ``browser``: the one profile every run uses (its cache kept, as a user's browser)."""
    # logged in again each run: both servers are on 127.0.0.1, and cookies ignore the port
    r = browser.request.post(
        f"{target.url}/api/auth/login", data={"username": "admin", "password": PASSWORD}
    )
    assert r.status == 200, r.text()
    page = browser.new_page()
    try:
        page.set_default_timeout(120_000)
        page.goto(f"{target.url}/volumes/{target.volume}")
        page.wait_for_selector("body[data-ready='1']")
        page.fill("#threshold", str(level))
        time.sleep(0.5)  # the page settles (slice previews, histogram) as a user's would
        page.click("#generate")
        page.wait_for_url("**/models/*")
        page.wait_for_function(
            f"""() => {{
                const p = window.__probe, m = window.__miss;
                return p && m && p.frames.some((f) => f.share > {DRAWN} && f.drawn !== 'preview')
                    && (m.ready || m.drawn === 'full');
            }}"""
        )
        click = float(page.evaluate("() => sessionStorage.getItem('clickAt')"))
        frames = page.evaluate("() => window.__probe.frames")
        model_id = page.url.rstrip("/").split("/")[-1].split("?")[0]
        model = wait_done(target, model_id)
        turns = turn(page)
    finally:
        page.close()
    drawn = [f for f in frames if f["share"] > DRAWN]
    full = next(f for f in drawn if f["drawn"] != "preview")
    time.sleep(LOOK)
    seconds = model["stats"]["seconds"]
    # The job's time until the model's GLB existed: reported as such, or (a server that
    # wrote every format before any was served) everything before the measurement.
    job = model["stats"].get("ready_seconds")
    if job is None:
        job = sum(v for k, v in seconds.items() if k not in ("total", "measure"))
    return {
        "level": level,
        "first_s": (drawn[0]["t"] - click) / 1000,
        "first_kind": drawn[0]["drawn"] or "full",
        "full_s": (full["t"] - click) / 1000,
        "job_s": job,
        "triangles": model["stats"]["triangles"],
        "seconds": seconds,
        "turn_s": statistics.median(turns),
        # the job's wait for the page to draw its model (miss.server.jobs.turn), and its
        # whole time from submission to done
        "held_s": seconds.get("viewer", 0.0),
        "done_s": (
            datetime.fromisoformat(model["finished"]) - datetime.fromisoformat(model["created"])
        ).total_seconds(),
    }


def turn(page: Any) -> list[float]:
    """Seconds from a drag's move on the drawn model (the job done) until the turned model's
    pixels, ``TURNS`` times: what a physician waits for at each step of turning it."""
    box = page.locator("#stage canvas").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    seconds = []
    for _ in range(TURNS):
        time.sleep(0.3)
        page.mouse.move(x, y)
        page.mouse.down()
        page.mouse.move(x + 40, y, steps=1)
        page.wait_for_function("() => window.__probe.frames.some((f) => f.t > window.__turnAt)")
        at, frames = page.evaluate("() => [window.__turnAt, window.__probe.frames]")
        page.mouse.up()
        seconds.append((next(f["t"] for f in frames if f["t"] > at) - at) / 1000)
    return seconds


def wait_done(target: Target, model_id: str, timeout: float = 300) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        model = target.model(model_id)
        if model["status"] in ("done", "failed"):
            assert model["status"] == "done", model
            return model
        time.sleep(0.2)
    raise RuntimeError(f"model {model_id} not done after {timeout} s")


def summary(target: Target) -> list[Any]:
    runs = target.runs
    med = {
        k: statistics.median(r.get(k, 0.0) for r in runs)
        for k in ("first_s", "full_s", "job_s", "turn_s", "held_s", "done_s")
    }
    kinds = sorted({r["first_kind"] for r in runs})
    return [
        target.name,
        len(runs),
        med["first_s"],
        "/".join(kinds),
        med["full_s"],
        med["job_s"],
        # each run's own difference (its job and its drawing), then their median: the
        # difference of the two medians pairs figures from different runs
        statistics.median(r["full_s"] - r["job_s"] for r in runs),
        int(statistics.median(r["triangles"] for r in runs)),
        med["turn_s"],
        med["held_s"],
        med["done_s"],
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--baseline", type=Path, help="another source tree to compare with")
    args = parser.parse_args(argv)
    if not CTHEAD.is_file():
        print(f"first_pixels: the CThead is not at {CTHEAD} (../shared/datasets)", file=sys.stderr)
        return 2
    from playwright.sync_api import sync_playwright

    work = Path(tempfile.mkdtemp(prefix="miss-first-pixels-"))
    targets: list[Target] = []
    try:
        targets.append(Target("this tree", None, work))
        if args.baseline:
            targets.append(Target(f"baseline {args.baseline}", args.baseline.resolve(), work))
        with sync_playwright() as p:
            # One profile on disk for every run, as a user's browser: its cache and the
            # code compiled from it kept (a new context each run had neither)
            browser = p.chromium.launch_persistent_context(
                work / "profile", executable_path=CHROMIUM, args=CHROMIUM_ARGS, viewport=LAPTOP
            )
            browser.add_init_script(PROBE)
            for i in range(args.runs + 1):  # the first round warms the browser's cache
                for target in targets:
                    run = one_run(browser, target, BONE + i)
                    if i:
                        target.runs.append(run)
                    print(
                        target.name,
                        {k: run[k] for k in ("first_s", "full_s", "job_s", "turn_s", "held_s")},
                    )
            browser.close()
    finally:
        for target in targets:
            target.stop()
        shutil.rmtree(work, ignore_errors=True)
    header = ["server", "runs", "first pixels s", "first drawn", "full model s", "job s",
              "full - job s", "triangles", "turn s", "held s", "done s"]  # fmt: skip
    rows = [summary(t) for t in targets]
    table = markdown_table(header, rows)
    if len(targets) == 2:
        a, b = rows
        table += (
            f"\nbaseline / this tree: first pixels {b[2] / a[2]:.2f}x, "
            f"full model {b[4] / a[4]:.2f}x, a turn {b[8] / a[8]:.2f}x "
            f"(medians of {args.runs} alternating runs)\n"
        )
    print(table)
    save("first_pixels", {"runs": {t.name: t.runs for t in targets}}, table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
