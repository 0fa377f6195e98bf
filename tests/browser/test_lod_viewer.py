"""Levels of detail in the browser: a model over the server's triangle budget is drawn
from its tileset, coarse first; zooming in refines the tiles in view (more triangles
drawn), zooming out coarsens again (fewer)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from browser.conftest import Server, laptop_page, serve

BUDGET = 20_000


@pytest.fixture(scope="module")
def lod_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    with serve(tmp_path_factory, MISS_LOD_TRIANGLES=str(BUDGET)) as running:
        yield running


def settled(page: Any) -> int:
    """Triangles drawn once no tile is loading any more and two frames have passed."""
    for _ in range(100):
        page.evaluate(
            "() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))"
        )
        if page.evaluate("() => window.__miss.lod.loading") == 0:
            page.evaluate(
                "() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))"
            )
            if page.evaluate("() => window.__miss.lod.loading") == 0:
                return int(page.evaluate("() => window.__miss.drawnTriangles"))
        time.sleep(0.1)
    raise AssertionError(f"tiles still loading: {page.evaluate('() => window.__miss.lod')}")


def zoom(page: Any, clicks: int) -> None:
    """Mouse-wheel clicks over the middle of the canvas (negative: in)."""
    box = page.locator("#stage canvas").bounding_box()
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    for _ in range(abs(clicks)):
        page.mouse.wheel(0, 100 if clicks > 0 else -100)
        page.wait_for_timeout(30)


def test_coarse_first_then_refined_when_zoomed_in(
    browser: Any, lod_server: Server, artifacts: Path
) -> None:
    volumes = lod_server.get("/api/volumes")
    demo = next(v for v in volumes if "phantom" in v["name"].lower())
    body = {"volume": demo["id"], "level": 300, "decimate": "none"}
    model = lod_server.wait_model(lod_server.post("/api/models", body)["id"])
    assert model["status"] == "done", model["error"]
    assert model["stats"]["triangles"] > BUDGET and model["lod"]
    with laptop_page(browser, lod_server) as page:
        start = time.monotonic()
        page.goto(f"/models/{model['id']}")
        page.wait_for_function("() => window.__miss.ready && window.__miss.drawnTriangles > 0")
        first_draw = time.monotonic() - start
        # the first frame's count, kept by the page: tiles may refine before this call
        first = page.evaluate("() => window.__miss.firstDrawnTriangles")
        root = lod_server.get(model["lod"].split("?")[0])["root"]
        assert first == root["extras"]["triangles"] < BUDGET  # the coarse root, alone
        assert first_draw < 10
        fitted = settled(page)
        (artifacts / "lod-fitted.png").write_bytes(page.locator("#stage canvas").screenshot())
        zoom(page, -20)
        zoomed = settled(page)
        (artifacts / "lod-zoomed.png").write_bytes(page.locator("#stage canvas").screenshot())
        assert zoomed > fitted >= first
        assert "levels of detail" in page.inner_text("#drawn")
        # What is drawn is what is picked, and a part hidden is hidden in every tile.
        box = page.locator("#stage canvas").bounding_box()
        page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
        page.wait_for_function("() => window.__miss.structures.selected === 0")
        assert "mL" in page.inner_text("#part-info")
        assert not page.is_visible("#part-download")  # the page holds no part at full resolution
        page.locator("#structure-list li").nth(0).locator("[data-role=visible]").uncheck()
        assert settled(page) == 0
        page.locator("#structure-list li").nth(0).locator("[data-role=visible]").check()
        assert settled(page) == zoomed
        page.click("#fit")
        back = settled(page)
        zoom(page, 8)
        far = settled(page)
        (artifacts / "lod-far.png").write_bytes(page.locator("#stage canvas").screenshot())
        assert far <= back < zoomed
        print(
            f"first draw {first_draw:.2f} s, {first} triangles; fitted {fitted}, "
            f"zoomed in {zoomed}, fitted again {back}, far {far}; "
            f"{model['stats']['lod']['tiles']} tiles, {model['stats']['lod']['bytes']} bytes "
            f"(GLB {model['files']['glb']['bytes']})"
        )


def test_a_running_jobs_page_draws_the_levels_of_detail_not_the_glb(
    browser: Any, lod_server: Server
) -> None:
    """Opened while the job runs: the preview, then the tileset (written before the GLB);
    the model's GLB, too large to draw, is never fetched."""
    volumes = lod_server.get("/api/volumes")
    demo = next(v for v in volumes if "phantom" in v["name"].lower())
    body = {"volume": demo["id"], "level": 250, "decimate": "none"}
    model = lod_server.post("/api/models", body)
    with laptop_page(browser, lod_server) as page:
        fetched: list[str] = []
        page.on("request", lambda r: fetched.append(r.url))
        page.goto(f"/models/{model['id']}")
        page.wait_for_function("() => window.__miss.ready", timeout=120_000)
        assert lod_server.get(f"/api/models/{model['id']}")["status"] == "done"
        assert page.evaluate("() => window.__miss.lod.tiles") >= 1
        assert settled(page) > 0
    assert any("/lod/tileset.json" in url for url in fetched)
    assert not any("/model.glb" in url for url in fetched), fetched


def test_a_links_guest_sees_a_scene_of_parts_from_its_levels_of_detail(
    browser: Any, lod_server: Server, artifacts: Path
) -> None:
    """Two coloured parts over the budget, opened from a share link (no login): drawn from
    the tileset, both parts listed with their own colours, refined when zoomed in."""
    volumes = lod_server.get("/api/volumes")
    demo = next(v for v in volumes if "phantom" in v["name"].lower())
    parts = [
        {"level": 300, "name": "bone", "color": "#e0d4b0"},
        {"level": -500, "name": "skin", "color": "#c08070", "opacity": 0.4},
    ]
    body = {"volume": demo["id"], "decimate": "none", "parts": parts}
    model = lod_server.wait_model(lod_server.post("/api/models", body)["id"])
    assert model["status"] == "done", model["error"]
    assert model["lod"]
    link = lod_server.post("/api/shares", {"model": model["id"]})
    context = browser.new_context(base_url=lod_server.url, viewport={"width": 1366, "height": 768})
    try:
        guest = context.new_page()
        guest.goto(link["url"])
        guest.wait_for_function(
            "() => window.__miss.ready && window.__miss.lod && window.__miss.structures.parts.length === 2"
        )
        listed = guest.evaluate("() => window.__miss.structures.parts")
        assert [p["name"] for p in listed] == ["bone", "skin"]
        assert [p["color"] for p in listed] == ["#e0d4b0", "#c08070"]
        assert listed[1]["opacity"] == 0.4
        fitted = settled(guest)
        guest.locator("#stage canvas").screenshot(path=artifacts / "lod-guest-parts.png")
        zoom(guest, -20)
        assert settled(guest) > fitted
    finally:
        context.close()
