"""The pages as a physician uses them: upload, choose a threshold, generate, view, download.

Driven through Debian's chromium against a real ``miss serve``; screenshots land in
test-artifacts/browser/ so a person can look at what the tests saw.
"""

from __future__ import annotations

import base64
import io
import json
import os
import struct
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh
from PIL import Image

LAPTOP = {"width": 1366, "height": 768}
REPO = Path(__file__).resolve().parents[2]
DATASETS = Path(os.environ.get("MISS_DATASETS", REPO.parent / "shared" / "datasets"))
PAD = 8  # histogram.js: horizontal padding of the plot inside the canvas, CSS px


def _rgb(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)


def non_background(png: bytes, background: str) -> float:
    """Fraction of the central region (away from the corner gizmo) not of the background colour."""
    img = _rgb(png)
    h, w, _ = img.shape
    centre = img[h // 5 : h - h // 5, w // 5 : w - w // 5]
    bg = np.array([int(background[i : i + 2], 16) for i in (1, 3, 5)])
    return float((np.abs(centre - bg).max(axis=2) > 16).mean())


def tinted(png: bytes) -> int:
    """Pixels carrying the server's orange threshold tint (red well above blue)."""
    img = _rgb(png)
    return int(((img[..., 0] - img[..., 2]) > 60).sum())


def wait_drawn(page: Any, mode: str) -> dict[str, Any]:
    page.wait_for_function(
        "mode => window.__miss && window.__miss.ready && window.__miss.mode === mode",
        arg=mode,
        timeout=90_000,
    )
    return page.evaluate("() => ({...window.__miss})")


def drop_file(page: Any, path: Path) -> None:
    """Drop a file on the library page as a person dragging it from the desktop would."""
    page.evaluate(
        """([name, b64]) => {
            const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
            const data = new DataTransfer();
            data.items.add(new File([bytes], name));
            const zone = document.getElementById('dropzone');
            for (const type of ['dragenter', 'dragover', 'drop']) {
                zone.dispatchEvent(new DragEvent(type, {bubbles: true, cancelable: true, dataTransfer: data}));
            }
        }""",
        [path.name, base64.b64encode(path.read_bytes()).decode()],
    )


def upload_via_library(
    browser: Any, server: Any, path: Path, artifacts: Path, how: str, logged_in: Any
) -> dict[str, Any]:
    """Upload through the library page (file picker or drop); the new volume's JSON."""
    context = browser.new_context(viewport=LAPTOP, base_url=server.url)
    logged_in(context)
    page = context.new_page()
    try:
        page.goto("/")
        page.wait_for_selector("body[data-ready='1']")
        known = set(
            page.eval_on_selector_all(".volume-card", "cards => cards.map(c => c.dataset.id)")
        )
        if how == "drop":
            drop_file(page, path)
        else:
            page.set_input_files("#file-input", str(path))
        page.wait_for_selector("#upload-progress[data-done]", timeout=90_000)
        assert page.eval_on_selector("#upload-progress", "bar => bar.value") == 1
        ids = page.eval_on_selector_all(".volume-card", "cards => cards.map(c => c.dataset.id)")
        (volume_id,) = set(ids) - known
        page.wait_for_function(
            "() => [...document.querySelectorAll('.volume-card img')].every(i => i.complete && i.naturalWidth > 0)"
        )
        page.screenshot(path=artifacts / f"library-after-{how}.png")
    finally:
        context.close()
    return server.get(f"/api/volumes/{volume_id}")


@pytest.fixture(scope="module")
def uploaded(
    browser: Any, server: Any, phantom: Path, artifacts: Path, logged_in: Any
) -> dict[str, Any]:
    """The synthetic head (NIfTI) dropped on the library page."""
    return upload_via_library(browser, server, phantom, artifacts, "drop", logged_in)


@pytest.fixture(scope="module")
def head_ct(
    browser: Any,
    server: Any,
    tmp_path_factory: pytest.TempPathFactory,
    artifacts: Path,
    uploaded: dict[str, Any],
    logged_in: Any,
) -> dict[str, Any]:
    """A real head CT: the zipped DICOM series from ../shared/datasets chosen with the
    file picker; without the datasets, the phantom (whose NIfTI carries no HU units)."""
    folder = DATASETS / "ct_head_dicom_ge_gantrytilt"
    if not folder.is_dir():
        return uploaded
    archive = tmp_path_factory.mktemp("zip") / "head-ct-dicom.zip"
    with zipfile.ZipFile(archive, "w") as zf:
        for file in sorted(folder.iterdir()):
            zf.write(file, f"series/{file.name}")
    return upload_via_library(browser, server, archive, artifacts, "picker", logged_in)


def test_upload_from_library_lists_the_volume(page: Any, uploaded: dict[str, Any]) -> None:
    assert uploaded["dims"] == [128, 128, 128]
    page.goto("/")
    card = page.locator(f".volume-card[data-id='{uploaded['id']}']")
    card.wait_for()
    assert "128 × 128 × 128" in card.inner_text()
    thumb = card.locator("img")
    thumb.wait_for()
    # The thumbnail loads lazily: wait until the browser has finished with it (loaded or
    # broken), then ask whether it decoded to an image.
    handle = thumb.element_handle()
    page.wait_for_function("img => img.complete", arg=handle)
    assert page.evaluate("img => img.naturalWidth > 0", handle)


def test_threshold_drag_retints_the_slices(
    page: Any, server: Any, uploaded: dict[str, Any], artifacts: Path
) -> None:
    page.goto(f"/volumes/{uploaded['id']}")
    page.wait_for_selector("body[data-ready='1']")
    axial = page.locator(".view[data-axis=axial] img")
    shown = "t => (document.querySelector('.view[data-axis=axial] img').dataset.loaded || '').includes('threshold=' + t)"
    start = float(page.input_value("#threshold"))
    page.wait_for_function(shown, arg=page.input_value("#threshold"))
    bone = axial.screenshot()

    # Drag the histogram's threshold line down to -200 HU: soft tissue joins bone.
    hist = server.get(f"/api/volumes/{uploaded['id']}/histogram")
    edges = hist["edges"] if "edges" in hist else hist["bins"]
    box = page.locator("#histogram").bounding_box()
    y = box["y"] + box["height"] / 2

    def x_of(value: float) -> float:
        return (
            box["x"] + PAD + (value - edges[0]) / (edges[-1] - edges[0]) * (box["width"] - 2 * PAD)
        )

    page.mouse.move(x_of(start), y)
    page.mouse.down()
    page.mouse.move(x_of(-200), y, steps=8)
    page.mouse.up()
    level = float(page.input_value("#threshold"))
    assert abs(level - -200) < 20, level
    assert page.get_attribute("#presets [data-preset=custom]", "aria-pressed") == "true"
    page.wait_for_function(shown, arg=page.input_value("#threshold"))
    soft = axial.screenshot()
    page.screenshot(path=artifacts / "volume-threshold-soft.png")
    assert soft != bone
    assert tinted(soft) > 2 * tinted(bone) > 0


def test_generate_view_and_download(
    page: Any, server: Any, head_ct: dict[str, Any], artifacts: Path
) -> None:
    nz = head_ct["dims"][2]
    page.goto(f"/volumes/{head_ct['id']}")
    page.wait_for_selector("body[data-ready='1']")
    page.click("#presets [data-preset=bone]")
    if head_ct.get("units") != "HU":  # the phantom's NIfTI: its "bone" is only a percentile
        page.fill("#threshold", "300")
    assert float(page.input_value("#threshold")) == 300
    page.fill("#sample-rate", "2")
    assert page.input_value("#decimate") == "quadric"
    assert float(page.input_value("#error-bound")) == 0.002
    assert float(page.input_value("#reduce")) == 0.9
    # the ranges from the API's schema (miss.spec), as the markup had them
    assert page.get_attribute("#error-bound", "max") == "0.01"
    assert page.get_attribute("#reduce", "max") == "0.99"

    # Drag the end line on the sagittal view down a quarter: the top of the skull is cut off.
    page.wait_for_selector(".view[data-axis=sagittal] img[data-loaded]")
    frame = page.locator(".view[data-axis=sagittal] .frame").bounding_box()
    line = page.locator(".range-line.end").bounding_box()
    x, y = line["x"] + line["width"] / 3, line["y"] + line["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x, y + frame["height"] / 4, steps=6)
    page.mouse.up()
    end = int(page.input_value("#end-slice"))
    assert nz * 0.65 < end < nz * 0.85, end
    page.screenshot(path=artifacts / "volume-page.png")

    said: list[str] = []  # the page's word that it drew the running job's model
    page.on("request", lambda r: said.append(r.url) if r.url.endswith("/shown") else None)
    page.click("#generate")
    page.wait_for_url("**/models/*")  # at once: the model's page follows the job
    model_id = page.url.rstrip("/").split("/")[-1].split("?")[0]
    model = server.wait_model(model_id, timeout=150)
    assert model["status"] == "done"
    assert model["params"]["end_slice"] == end
    assert model["params"]["level"] == 300
    triangles = model["stats"]["triangles"]

    glb = wait_drawn(page, "glb")  # (Playwright calls also deliver the page's requests)
    assert glb["triangles"] == triangles
    # The job held back its other work for the page (miss.server.jobs.turn): the page's
    # word ended the wait when it came before the second was up, and came only for a
    # model drawn while the job ran, that is while the job waited.
    held = model["stats"]["seconds"].get("viewer")
    if held is not None and held < 0.9:
        assert said == [f"{server.url}/api/models/{model_id}/shown"], (held, said)
    if said:
        assert held is not None, said
    # what made the model and whether it is within its bound, as the physician reads it
    decimation = model["stats"]["decimation"]
    stats, params = page.inner_text("#stats"), page.inner_text("#params")
    assert "quadric asked; made by schroeder" in params
    assert f"yes: within {decimation['bound_mm']:.3f} mm; stopped by the" in stats
    shot = page.locator("#stage canvas").screenshot()
    page.screenshot(path=artifacts / "viewer-glb.png")
    assert non_background(shot, glb["backgroundColor"]) > 0.05

    page.click("[data-mode=vrml]")
    vrml = wait_drawn(page, "vrml")
    assert vrml["triangles"] == triangles
    shot = page.locator("#stage canvas").screenshot()
    page.screenshot(path=artifacts / "viewer-vrml.png")
    assert non_background(shot, vrml["backgroundColor"]) > 0.05
    assert "mode=vrml" in page.url

    page.click("#background")
    assert page.evaluate("() => window.__miss.background") == "light"
    shot = page.locator("#stage canvas").screenshot()
    page.screenshot(path=artifacts / "viewer-vrml-light.png")
    assert non_background(shot, page.evaluate("() => window.__miss.backgroundColor")) > 0.05

    with page.expect_download() as info:
        page.click("#downloads a[data-format=stl]")
    download = info.value
    data = Path(download.path()).read_bytes()
    assert download.suggested_filename.endswith(".stl")
    (count,) = struct.unpack_from("<I", data, 80)
    assert count == triangles and len(data) == 84 + 50 * count

    with page.expect_download() as info:
        page.click("#downloads a[data-format=wrl]")
    assert Path(info.value.path()).read_bytes().startswith(b"#VRML V2.0 utf8")

    # Beside the viewer's compressed .glb, a plain one that tools without meshopt open.
    plain = page.locator("#downloads a[data-format='plain.glb']")
    assert plain.inner_text().startswith("GLB (plain, opens anywhere)")
    with page.expect_download() as info:
        plain.click()
    assert info.value.suggested_filename.endswith(".plain.glb")
    data = Path(info.value.path()).read_bytes()
    document = json.loads(data[20 : 20 + struct.unpack_from("<I", data, 12)[0]])
    assert "extensionsRequired" not in document
    loaded = trimesh.load(io.BytesIO(data), file_type="glb", process=False)
    assert sum(len(m.faces) for m in loaded.geometry.values()) == triangles


def test_generate_shows_the_model_page_in_the_same_document(
    page: Any, server: Any, uploaded: dict[str, Any], artifacts: Path
) -> None:
    """Generate shows the model's page without loading a new one: its modules were loaded
    while the user chose, its markup is the server's (whose request records the view, as
    opening the page does), and it works as when opened from its address. Back goes to
    the volume's page, loaded anew."""
    page.goto(f"/volumes/{uploaded['id']}")
    page.wait_for_selector("body[data-ready='1']")
    page.fill("#threshold", "300")
    page.fill("#sample-rate", "2")
    page.wait_for_function(
        """() => performance.getEntriesByType('resource')
            .some((e) => e.name.endsWith('/static/js/pages/viewer-page.js'))"""
    )
    page.evaluate("() => { window.__sameDocument = true; }")
    page.click("#generate")
    page.wait_for_url("**/models/*")
    model_id = page.url.rstrip("/").split("/")[-1]
    assert server.wait_model(model_id, timeout=150)["status"] == "done"
    glb = wait_drawn(page, "glb")
    assert page.evaluate("() => window.__sameDocument") is True
    assert glb["triangles"] > 0
    assert page.evaluate("() => document.body.className") == "owner"
    assert page.title() == f"MISS · {uploaded['name']}"
    assert page.locator("#downloads a").count() == 9  # every format, the plain GLB too
    assert page.is_visible("#volume-link") and not page.is_visible("#generate")
    page.screenshot(path=artifacts / "viewer-same-document.png")
    views = server.get("/api/audit?action=view")
    assert [e["target"] for e in views].count(model_id) == 1

    page.go_back()
    page.wait_for_selector("body[data-ready='1']")
    assert page.url.endswith(f"/volumes/{uploaded['id']}")
    assert page.evaluate("() => window.__sameDocument") is None
    assert page.is_visible("#generate")


def _finished_model(server: Any, volume_id: str) -> str:
    """A done model of the volume: the one the generate test made, else a fresh one."""
    listed = server.get(f"/api/models?volume={volume_id}")
    models = listed if isinstance(listed, list) else listed.get("models", listed.get("items", []))
    done = [m for m in models if m["status"] == "done"]
    if done:
        return done[0]["id"]
    job = server.post("/api/models", {"volume": volume_id, "level": 300, "sample_rate": 2})
    assert server.wait_model(job["id"])["status"] == "done"
    return job["id"]


def test_viewer_on_a_tablet_turns_by_touch(
    browser: Any, server: Any, uploaded: dict[str, Any], artifacts: Path, logged_in: Any
) -> None:
    model_id = _finished_model(server, uploaded["id"])
    context = browser.new_context(
        viewport={"width": 1024, "height": 768}, has_touch=True, is_mobile=True, base_url=server.url
    )
    logged_in(context)
    page = context.new_page()
    try:
        page.goto(f"/models/{model_id}")
        state = wait_drawn(page, "glb")
        canvas = page.locator("#stage canvas")
        box = canvas.bounding_box()
        assert box["width"] >= 600 and box["height"] >= 600
        before = canvas.screenshot()
        page.screenshot(path=artifacts / "viewer-tablet.png")
        assert non_background(before, state["backgroundColor"]) > 0.05

        # One finger across the canvas orbits the model (OrbitControls' touch rotate).
        cdp = context.new_cdp_session(page)
        cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        cdp.send(
            "Input.dispatchTouchEvent", {"type": "touchStart", "touchPoints": [{"x": cx, "y": cy}]}
        )
        for step in range(1, 9):
            point = {"x": cx + 25 * step, "y": cy}
            cdp.send("Input.dispatchTouchEvent", {"type": "touchMove", "touchPoints": [point]})
        cdp.send("Input.dispatchTouchEvent", {"type": "touchEnd", "touchPoints": []})
        page.wait_for_timeout(300)  # the render is queued for the next animation frame
        after = canvas.screenshot()
        page.screenshot(path=artifacts / "viewer-tablet-turned.png")
        assert after != before
        assert page.locator("#downloads a").count() == 9  # every format, the plain GLB too
    finally:
        context.close()


def test_software_webgl_draws_without_multisampling(
    page: Any, server: Any, uploaded: dict[str, Any]
) -> None:
    """This chromium draws WebGL in software (SwiftShader, as a desktop without a GPU):
    the viewer asks for no multisampling there, which halved a full frame's time."""
    model_id = _finished_model(server, uploaded["id"])
    page.goto(f"/models/{model_id}")
    wait_drawn(page, "glb")
    renderer = page.evaluate(
        """() => {
            const gl = document.createElement('canvas').getContext('webgl2');
            const info = gl.getExtension('WEBGL_debug_renderer_info');
            return String(gl.getParameter(info.UNMASKED_RENDERER_WEBGL));
        }"""
    )
    assert "SwiftShader" in renderer
    assert page.evaluate("() => window.__miss.softwareWebGL") is True
    attributes = page.evaluate(
        "() => document.querySelector('#stage canvas').getContext('webgl2').getContextAttributes()"
    )
    assert attributes["antialias"] is False


def test_delete_from_library(page: Any, server: Any, phantom: Path) -> None:
    # The page's own session: a cookie, so the write carries the CSRF token as api.js does.
    csrf = next(c["value"] for c in page.context.cookies() if c["name"] == "miss_csrf")
    response = page.request.post(
        "/api/volumes",
        headers={"X-CSRF-Token": csrf},
        multipart={
            "file": {
                "name": "to-delete.nii.gz",
                "mimeType": "application/gzip",
                "buffer": phantom.read_bytes(),
            }
        },
    )
    assert response.status == 201, response.text()
    volume_id = response.json()["id"]
    page.goto("/")
    card = page.locator(f".volume-card[data-id='{volume_id}']")
    card.wait_for()
    page.once("dialog", lambda dialog: dialog.accept())
    card.locator("button.danger").click()
    card.wait_for(state="detached")
    assert page.request.get(f"/api/volumes/{volume_id}").status == 404
