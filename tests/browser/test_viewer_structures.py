"""Structures in the browser: a two-level scene (skin, translucent, and bone) made from
the volume page's form on the demo phantom, then the viewer's structure list: hiding
a part, changing its opacity and moving the clipping plane each change the picture;
clicking a part shows its measures; the selected part downloads on its own.

Screenshots go to test-artifacts/browser/structures-*.png.
"""

from __future__ import annotations

import io
import struct
import urllib.error
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

SET_RANGE = """([selector, value]) => {
    const input = document.querySelector(selector);
    input.value = String(value);
    input.dispatchEvent(new Event('input', { bubbles: true }));
}"""


def pixels(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)


def changed(a: bytes, b: bytes) -> float:
    """Fraction of the canvas's pixels that differ noticeably between two screenshots."""
    pa, pb = pixels(a), pixels(b)
    assert pa.shape == pb.shape
    return float((np.abs(pa - pb).max(axis=2) > 12).mean())


def canvas(page: Any, path: Path | None = None) -> bytes:
    """The canvas once the viewer has drawn the last change (two animation frames)."""
    page.evaluate("() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))")
    shot = page.locator("#stage canvas").screenshot()
    if path is not None:
        path.write_bytes(shot)
    return shot


def demo_volume(server: Any) -> dict[str, Any]:
    volumes = server.get("/api/volumes")
    demo = [v for v in volumes if "phantom" in v["name"].lower() or "demo" in v["name"].lower()]
    return (demo or volumes)[0]


def test_structures_in_the_viewer(page: Any, server: Any, artifacts: Path) -> None:
    volume = demo_volume(server)
    page.goto(f"/volumes/{volume['id']}")
    page.wait_for_selector("body[data-ready='1']")
    page.fill("#threshold", "300")
    page.fill("#structure-list [data-first] .structure-name", "bone")
    page.click("#add-structure")
    extra = page.locator("#structure-list li").nth(1)
    extra.locator(".structure-name").fill("skin")
    extra.locator(".structure-level").fill("-500")
    extra.locator(".structure-color").fill("#d9a07f")
    page.fill("#sample-rate", "2")
    page.screenshot(path=artifacts / "structures-volume-page.png")

    page.click("#generate")
    page.wait_for_url("**/models/*")  # at once: the model's page follows the job
    model_id = page.url.rstrip("/").split("/")[-1].split("?")[0]
    model = server.wait_model(model_id, timeout=180)
    assert model["status"] == "done"
    # Names and colours travel with the job and are written into the model by the server.
    assert model["params"]["parts"] == [
        {"level": 300, "name": "bone"},
        {"level": -500, "name": "skin", "color": "#d9a07f"},
    ]
    assert [p["name"] for p in model["stats"]["parts"]] == ["bone", "skin"]

    page.wait_for_function(
        "() => window.__miss.ready && window.__miss.structures.parts.length === 2",
        timeout=90_000,
    )
    parts = page.evaluate("() => window.__miss.structures.parts")
    assert [p["name"] for p in parts] == ["bone", "skin"]
    assert parts[1]["opacity"] < 1 and parts[0]["opacity"] == 1
    assert parts[1]["color"] == "#d9a07f"  # chosen on the volume page
    assert parts[0]["color"] != "#d9a07f"  # untouched: the server's bone colour
    assert all(p["volume_ml"] > 0 and p["area_cm2"] > 0 for p in parts)
    names = page.locator("#structure-list .part-name").all_inner_texts()
    assert names == ["bone", "skin"]

    before = canvas(page, artifacts / "structures-viewer.png")
    page.screenshot(path=artifacts / "structures-viewer-page.png")

    # Hide the bone: the picture changes; show it again.
    page.locator("#structure-list li").nth(0).locator("[data-role=visible]").uncheck()
    hidden = canvas(page, artifacts / "structures-bone-hidden.png")
    assert changed(before, hidden) > 0.01
    assert page.evaluate("() => window.__miss.structures.parts[0].visible") is False
    page.locator("#structure-list li").nth(0).locator("[data-role=visible]").check()
    assert changed(before, canvas(page)) < 0.002

    # Colour the bone red: the picture changes.
    page.locator("#structure-list li").nth(0).locator("[data-role=color]").fill("#c03030")
    red = canvas(page, artifacts / "structures-bone-red.png")
    assert changed(before, red) > 0.01
    assert page.evaluate("() => window.__miss.structures.parts[0].color") == "#c03030"
    before = red

    # Make the skin nearly opaque: the bone behind it fades.
    page.evaluate(SET_RANGE, ["#structure-list li:nth-child(2) [data-role=opacity]", 0.95])
    opaque = canvas(page, artifacts / "structures-skin-opaque.png")
    assert changed(before, opaque) > 0.01
    assert page.evaluate("() => window.__miss.structures.parts[1].opacity") == 0.95

    # An axial clipping plane halfway up cuts the head open; moving it changes the cut.
    page.select_option("#clip-axis", "axial")
    page.evaluate(SET_RANGE, ["#clip-position", 0.5])
    half = canvas(page, artifacts / "structures-clipped-half.png")
    assert changed(opaque, half) > 0.01
    page.evaluate(SET_RANGE, ["#clip-position", 0.3])
    lower = canvas(page, artifacts / "structures-clipped-lower.png")
    assert changed(half, lower) > 0.01
    assert page.evaluate("() => window.__miss.structures.clip") == {
        "axis": "axial",
        "fraction": 0.3,
    }

    # Click the lower middle (what the cut leaves): a part is selected and its measures shown.
    box = page.locator("#stage canvas").bounding_box()
    page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] * 0.78)
    page.wait_for_function("() => window.__miss.structures.selected !== null")
    selected = page.evaluate("() => window.__miss.structures.selected")
    info = page.inner_text("#part-info")
    assert parts[selected]["name"] in info and "mL" in info and "cm²" in info
    page.screenshot(path=artifacts / "structures-selected.png")

    # The selected part alone, as STL in patient millimetres, named after it.
    with page.expect_download() as download:
        page.click("[data-part-format=stl]")
    data = Path(download.value.path()).read_bytes()
    assert download.value.suggested_filename == f"{parts[selected]['name']}.stl"
    (count,) = struct.unpack_from("<I", data, 80)
    assert count > 100 and len(data) == 84 + 50 * count

    # The VRML file draws the same parts, named from the model's stats.
    page.click("[data-mode=vrml]")
    page.wait_for_function(
        "() => window.__miss.ready && window.__miss.mode === 'vrml'", timeout=90_000
    )
    names = page.evaluate("() => window.__miss.structures.parts.map((p) => p.name)")
    assert names == ["bone", "skin"]
    canvas(page, artifacts / "structures-vrml.png")


def test_split_and_largest_through_the_api(server: Any) -> None:
    """The structure fields pass through POST /api/models; stats list the parts."""
    volume = demo_volume(server)
    body = {"volume": volume["id"], "sample_rate": 4, "decimate": "none"}
    split = server.post(
        "/api/models", {**body, "levels": [300], "components": "split", "min_size_mm3": 50}
    )
    done = server.wait_model(split["id"])
    assert done["status"] == "done", done["error"]
    assert done["params"]["components"] == "split" and done["params"]["min_size_mm3"] == 50
    parts = done["stats"]["parts"]
    assert parts and all(p["volume_ml"] * 1000 >= 50 for p in parts)
    volumes = [p["volume_ml"] for p in parts]
    assert volumes == sorted(volumes, reverse=True)
    largest = server.wait_model(
        server.post("/api/models", {**body, "level": 300, "components": "largest"})["id"]
    )
    assert largest["status"] == "done" and len(largest["stats"]["parts"]) == 1
    assert largest["stats"]["parts"][0]["volume_ml"] == pytest.approx(volumes[0], rel=0.05)
    with pytest.raises(urllib.error.HTTPError) as bad:
        server.post("/api/models", {**body, "level": 300, "components": "some"})
    assert bad.value.code == 422


def test_label_map_uploaded_on_the_volume_page_becomes_parts(
    page: Any, server: Any, artifacts: Path, tmp_path: Path
) -> None:
    """The label-map section: upload a segmentation of the scan, tick all its labels,
    Generate: the model has one part per label (uploads go through api.request)."""
    import nibabel as nib
    import numpy as np

    from miss.demo import phantom

    scan = phantom()
    labels = np.zeros(scan.dims, dtype=np.uint8)
    labels[np.asarray(scan.data) > 300] = 1  # bone
    labels[(np.asarray(scan.data) > -500) & (np.asarray(scan.data) <= 300)] = 2  # the rest
    path = tmp_path / "seg.nii.gz"
    nib.save(nib.Nifti1Image(labels, np.diag([-1.0, -1.0, 1.0, 1.0]) @ scan.affine), path)

    volume = demo_volume(server)
    page.goto(f"/volumes/{volume['id']}")
    page.wait_for_selector("body[data-ready='1']")
    page.set_input_files("#labelmap input[type=file]", str(path))
    page.wait_for_function(
        "() => document.querySelectorAll('#labelmap .label-list li').length === 2"
    )
    assert "2 labels" in page.inner_text("#labelmap .label-status")
    page.check("#labelmap .label-all")
    page.fill("#sample-rate", "4")
    page.screenshot(path=artifacts / "labelmap-volume-page.png")
    page.click("#generate")
    page.wait_for_url("**/models/*")
    model = server.wait_model(page.url.rstrip("/").split("/")[-1].split("?")[0], timeout=180)
    assert model["status"] == "done", model["error"]
    assert model["params"]["labels"] == "all" and model["params"]["level"] is None
    assert [p["label"] for p in model["stats"]["parts"]] == [1, 2]
    page.wait_for_function(
        "() => window.__miss.ready && window.__miss.structures.parts.length === 2",
        timeout=90_000,
    )
    server.delete(f"/api/volumes/{volume['id']}/labelmap")


def test_one_model_page_for_its_owner_and_a_links_guests(
    page: Any, browser: Any, server: Any, artifacts: Path
) -> None:
    """model.html is both pages: the owner sees Share and past consultations, a guest
    the link's facts and the provenance; both get the structure list. A selected part
    downloads on its own only when the link allows downloads."""
    volume = demo_volume(server)
    body = {"volume": volume["id"], "sample_rate": 4, "decimate": "none"}
    parts = [{"level": 300, "name": "bone"}, {"level": -500, "name": "skin"}]
    model = server.wait_model(server.post("/api/models", {**body, "parts": parts})["id"])
    assert model["status"] == "done", model["error"]
    owner_only, guest_only = "#share-section", "#share-info"

    page.goto(f"/models/{model['id']}")
    page.wait_for_function("() => window.__miss.ready", timeout=90_000)
    assert page.is_visible(owner_only) and page.is_visible("#history")
    assert not page.is_visible(guest_only) and not page.is_visible("#provenance")

    for can_download in (False, True):
        link = server.post("/api/shares", {"model": model["id"], "can_download": can_download})
        context = browser.new_context(base_url=server.url, accept_downloads=True)
        guest = context.new_page()
        errors: list[str] = []
        guest.on("pageerror", lambda exc, errors=errors: errors.append(str(exc)))
        try:
            guest.goto(link["url"])
            guest.wait_for_function(
                "() => window.__miss.ready && window.__miss.structures.parts.length === 2",
                timeout=90_000,
            )
            assert guest.is_visible(guest_only) and guest.is_visible("#provenance")
            assert not guest.is_visible(owner_only) and not guest.is_visible("#history")
            names = guest.locator("#structure-list .part-name").all_inner_texts()
            assert names == ["bone", "skin"]
            guest.locator("#structure-list .part-name").nth(0).click()
            guest.wait_for_function("() => window.__miss.structures.selected === 0")
            assert "bone" in guest.inner_text("#part-info")
            assert guest.is_visible("#part-download") is can_download
            assert guest.is_visible("#download-section") is can_download
            guest.screenshot(path=artifacts / f"model-page-guest-download-{can_download}.png")
        finally:
            context.close()
        assert not errors, errors
