"""The scan itself in the model page's 3-D view: a synthetic CT (HU) with a 700 HU cube
in the middle and two 2000 HU beads at opposite corners; the model is the beads alone
(level 1500), so what shows where the cube projects is the volume rendering. Turning the
volume on paints the cube there and leaves air alone; the lung preset (nothing at 700 HU)
takes it away again, MIP shows it grey.

Screenshots go to test-artifacts/browser/volume-*.png.
"""

from __future__ import annotations

import base64
import io
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

N = 64
CUBE = slice(20, 44)


@pytest.fixture(scope="module")
def cube_scan(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    nib = pytest.importorskip("nibabel")
    data = np.full((N, N, N), -1000, dtype=np.int16)
    data[CUBE, CUBE, CUBE] = 700
    data[1:4, 1:4, 1:4] = data[-4:-1, -4:-1, -4:-1] = 2000
    path = tmp_path_factory.mktemp("cube") / "cube.nii.gz"
    nib.save(nib.Nifti1Image(data, np.diag([2.0, 2.0, 2.0, 1.0])), path)
    return path.read_bytes()


def upload_cube(page: Any, cube_scan: bytes) -> Any:
    """The cube scan posted through the page's own session (its CSRF token); the response."""
    csrf = next(c["value"] for c in page.context.cookies() if c["name"] == "miss_csrf")
    file = {"name": "cube.nii.gz", "mimeType": "application/gzip", "buffer": cube_scan}
    return page.request.post(
        "/api/volumes", headers={"X-CSRF-Token": csrf}, multipart={"file": file}
    )


def canvas(page: Any, path: Path) -> np.ndarray:
    """The canvas once the last change is drawn (two animation frames), as RGB."""
    page.evaluate("() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))")
    shot = page.locator("#stage canvas").screenshot()
    path.write_bytes(shot)
    return np.asarray(Image.open(io.BytesIO(shot)).convert("RGB"), dtype=np.int16)


def around(image: np.ndarray, xy: list[float], r: int = 3) -> np.ndarray:
    """Mean colour of a small square about a canvas point (CSS pixels = screenshot pixels)."""
    x, y = round(xy[0]), round(xy[1])
    return image[y - r : y + r + 1, x - r : x + r + 1].reshape(-1, 3).mean(axis=0)


def test_volume_rendering_of_a_bright_cube(
    page: Any, server: Any, cube_scan: bytes, artifacts: Path
) -> None:
    response = upload_cube(page, cube_scan)
    assert response.status == 201, response.text()
    volume_id = response.json()["id"]
    job = server.post("/api/models", {"volume": volume_id, "level": 1500, "decimate": "none"})
    assert server.wait_model(job["id"])["status"] == "done"

    page.goto(f"/models/{job['id']}")
    page.wait_for_function("() => window.__miss.ready === true")
    before = canvas(page, artifacts / "volume-off.png")
    page.click("#volume-toggle")
    page.wait_for_function("() => window.__miss.volume && window.__miss.volume.on")
    after = canvas(page, artifacts / "volume-bone.png")
    assert "view=volume" in page.url  # the address says what is shown
    assert not page.locator("#volume-full").is_visible()  # 64³ is its full resolution

    middle = page.evaluate(f"() => window.__miss.voxelToScreen([{N // 2}, {N // 2}, {N // 2}])")
    air = page.evaluate(f"() => window.__miss.voxelToScreen([8, {N - 8}, 8])")
    edge = [5.0, 5.0]  # the canvas's corner: outside the box
    assert np.abs(around(after, middle) - around(before, middle)).max() > 60
    assert np.abs(around(after, edge) - around(before, edge)).max() < 4
    assert np.abs(around(after, air) - around(before, air)).max() < 12
    assert page.evaluate("() => window.__miss.volume.preset") == "CT bone"

    page.select_option("#volume-preset", "CT lung")
    page.wait_for_function("() => window.__miss.volume.preset === 'CT lung'")
    lung = canvas(page, artifacts / "volume-lung.png")
    assert np.abs(around(lung, middle) - around(before, middle)).max() < 12  # nothing at 700 HU

    page.select_option("#volume-preset", "MIP")
    page.wait_for_function("() => window.__miss.volume.preset === 'MIP'")
    mip = canvas(page, artifacts / "volume-mip.png")
    grey = around(mip, middle)
    assert np.ptp(grey) < 10 and 100 < grey.mean() < 230, grey  # 700 HU, a 400/1600 window
    assert np.abs(around(mip, edge) - around(before, edge)).max() < 4
    assert np.abs(around(mip, air) - around(before, air)).max() < 12  # air lets through


def frame(page: Any, turn: float, path: Path) -> tuple[str, np.ndarray]:
    """The next frame after turning the camera by ``turn`` radians: its quality and RGB at
    the canvas's CSS size (the drawing buffer may be smaller: software WebGL)."""
    grabbed = page.evaluate(f"() => window.__miss.grabVolumeFrame({turn})")
    png = base64.b64decode(grabbed["png"].split(",", 1)[1])
    path.write_bytes(png)
    box = page.locator("#stage canvas").bounding_box()
    size = (round(box["width"]), round(box["height"]))
    image = Image.open(io.BytesIO(png)).convert("RGB").resize(size, Image.Resampling.NEAREST)
    return grabbed["quality"], np.asarray(image, np.int16)


def test_turning_draws_fast_frames_then_the_full_one(
    page: Any, server: Any, cube_scan: bytes, artifacts: Path
) -> None:
    response = upload_cube(page, cube_scan)
    assert response.status == 201, response.text()
    job = server.post("/api/models", {"volume": response.json()["id"], "level": 1500})
    assert server.wait_model(job["id"])["status"] == "done"
    page.goto(f"/models/{job['id']}?view=volume")  # a deep link
    page.wait_for_function("() => window.__miss.volume && window.__miss.volume.on")

    quality, still = frame(page, 0, artifacts / "volume-still.png")
    assert quality == "full"
    quality, moving = frame(page, 0.4, artifacts / "volume-turning.png")
    assert quality == "fast"
    middle = page.evaluate(f"() => window.__miss.voxelToScreen([{N // 2}, {N // 2}, {N // 2}])")
    edge = [5.0, 5.0]
    # The fast frame draws the volume where it now is, and the air around it as before.
    assert np.abs(around(moving, middle) - around(still, middle)).max() < 40
    assert np.abs(around(moving, middle) - around(moving, edge)).max() > 60
    assert np.abs(around(moving, edge) - around(still, edge)).max() < 4
    assert np.abs(moving - still).max(axis=2).mean() > 1  # the picture turned

    page.evaluate("() => window.__miss.timeSettledFrame(0)")  # the camera stops
    quality, settled = frame(page, 0, artifacts / "volume-settled.png")
    assert quality == "full"
    assert np.abs(around(settled, middle) - around(moving, middle)).max() < 40
    # Full quality: not the fast frame of the same view (drawn from fewer pixels and
    # samples, it differs along every edge), and what a fresh full frame draws.
    assert (np.abs(settled - moving).max(axis=2) > 20).mean() > 0.002
    quality, again = frame(page, 0, artifacts / "volume-again.png")
    assert quality == "full" and np.abs(again - settled).max() <= 2


def test_a_guest_sees_the_scan_only_when_the_link_offers_it(
    page: Any, browser: Any, server: Any, cube_scan: bytes, artifacts: Path
) -> None:
    """Issue 43: a link made with "may see the scan itself" shows the Volume section on the
    guest's page and draws the cube from ``/s/{token}/voxels``; a plain link shows no
    Volume section at all."""
    from conftest import LAPTOP

    response = upload_cube(page, cube_scan)
    volume_id = response.json()["id"]
    job = server.post("/api/models", {"volume": volume_id, "level": 1500, "decimate": "none"})
    assert server.wait_model(job["id"])["status"] == "done"
    plain = server.post("/api/shares", {"model": job["id"], "expires_in": 3600})
    scan = server.post(
        "/api/shares", {"model": job["id"], "expires_in": 3600, "can_view_volume": True}
    )
    context = browser.new_context(viewport=LAPTOP, base_url=server.url)
    try:
        guest = context.new_page()
        guest.goto(plain["url"])
        guest.wait_for_function("() => window.__miss.ready === true")
        assert not guest.locator("#volume-toggle").is_visible()

        guest.goto(scan["url"])
        guest.wait_for_function("() => window.__miss.ready === true")
        assert "the scan in 3-D" in guest.locator("body").inner_text()
        before = canvas(guest, artifacts / "volume-guest-off.png")
        guest.click("#volume-toggle")
        guest.wait_for_function("() => window.__miss.volume && window.__miss.volume.on")
        after = canvas(guest, artifacts / "volume-guest-on.png")
        middle = guest.evaluate(
            f"() => window.__miss.voxelToScreen([{N // 2}, {N // 2}, {N // 2}])"
        )
        assert np.abs(around(after, middle) - around(before, middle)).max() > 60
    finally:
        context.close()


def test_a_room_follows_the_scans_view(
    page: Any, browser: Any, server: Any, cube_scan: bytes, artifacts: Path
) -> None:
    """Issue 43: rooms follow the volume view like the camera: the owner turns the scan on
    and picks a preset, and a guest in the room (a link that offers the scan) sees the same,
    the cube drawn on their canvas; a reload gives the owner the view back."""
    from conftest import owner_and_guest

    response = upload_cube(page, cube_scan)
    volume_id = response.json()["id"]
    job = server.post("/api/models", {"volume": volume_id, "level": 1500, "decimate": "none"})
    assert server.wait_model(job["id"])["status"] == "done"
    with owner_and_guest(page, browser, server, job["id"]) as guest:
        before = canvas(guest, artifacts / "volume-room-off.png")
        page.click("#volume-toggle")
        guest.wait_for_function("() => window.__miss.volume && window.__miss.volume.on")
        middle = guest.evaluate(
            f"() => window.__miss.voxelToScreen([{N // 2}, {N // 2}, {N // 2}])"
        )
        after = canvas(guest, artifacts / "volume-room-on.png")
        assert np.abs(around(after, middle) - around(before, middle)).max() > 60
        assert guest.locator("#volume-toggle").get_attribute("aria-pressed") == "true"

        page.wait_for_function("() => window.__miss.volume && window.__miss.volume.on")
        page.select_option("#volume-preset", "CT lung")
        guest.wait_for_function("() => window.__miss.volume.preset === 'CT lung'")
        assert guest.locator("#volume-preset").input_value() == "CT lung"
        page.fill("#volume-level", "250")
        guest.wait_for_function("() => window.__miss.volume.level === 250")
        page.click("#tf-editor summary")  # an edited transfer function reaches the guest too
        page.focus("#tf-canvas")
        page.keyboard.press("PageDown")
        for _ in range(5):
            page.keyboard.press("ArrowUp")
        page.wait_for_function("() => window.__miss.volume.preset === 'Custom'")
        guest.wait_for_function("() => window.__miss.volume.preset === 'Custom'")
        mine = page.evaluate("() => window.__miss.transfer.points")
        guest.wait_for_function(
            "(p) => JSON.stringify(window.__miss.transfer.points.map((q) => q[4].toFixed(3)))"
            " === JSON.stringify(p.map((q) => q[4].toFixed(3)))",
            arg=mine,
        )
        page.fill("#volume-level", "250")  # after the edit, as before it

        page.goto(f"/models/{job['id']}")  # no ?view= in the address: the room's view
        page.wait_for_function("() => window.__miss.volume && window.__miss.volume.level === 250")
        assert page.evaluate("() => window.__miss.volume.preset") == "Custom"
        page.click("#volume-toggle")
        guest.wait_for_function("() => !window.__miss.volume.on")


def drag_point(page: Any, index: int, to: tuple[float, float]) -> None:
    """Drags transfer-function point ``index`` to ``to`` (fractions of the editor's canvas
    across and down), as a mouse would."""
    box = page.locator("#tf-canvas").bounding_box()
    px = page.evaluate("() => window.__miss.transfer.pixels")
    scale = box["width"] / page.evaluate("() => document.getElementById('tf-canvas').width")
    x, y = box["x"] + px[index][0] * scale, box["y"] + px[index][1] * scale
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(box["x"] + to[0] * box["width"], box["y"] + to[1] * box["height"], steps=4)
    page.mouse.up()


def test_the_transfer_function_is_edited_on_the_histogram(
    page: Any, server: Any, cube_scan: bytes, artifacts: Path
) -> None:
    """Issue 43: an editable transfer function: dragging every point of the opacity curve to
    the bottom leaves the cube transparent; a point added (double-click) at the cube's
    700 HU and coloured green paints it green. The edit is the "Custom" preset."""
    response = upload_cube(page, cube_scan)
    volume_id = response.json()["id"]
    job = server.post("/api/models", {"volume": volume_id, "level": 1500, "decimate": "none"})
    assert server.wait_model(job["id"])["status"] == "done"
    page.goto(f"/models/{job['id']}")
    page.wait_for_function("() => window.__miss.ready === true")
    before = canvas(page, artifacts / "volume-tf-off.png")
    page.click("#volume-toggle")
    page.wait_for_function("() => window.__miss.volume && window.__miss.volume.on")
    middle = page.evaluate(f"() => window.__miss.voxelToScreen([{N // 2}, {N // 2}, {N // 2}])")
    page.select_option("#volume-preset", "CT soft tissue")
    page.wait_for_function("() => window.__miss.volume.preset === 'CT soft tissue'")
    shown = canvas(page, artifacts / "volume-tf-soft.png")
    assert np.abs(around(shown, middle) - around(before, middle)).max() > 60

    page.click("#tf-editor summary")
    count = len(page.evaluate("() => window.__miss.transfer.points"))
    for i in range(count):
        x = page.evaluate(f"() => window.__miss.transfer.pixels[{i}][0]") / 560
        drag_point(page, i, (x, 0.99))
    page.wait_for_function("() => window.__miss.transfer.points.every((p) => p[4] === 0)")
    page.wait_for_function("() => window.__miss.volume.preset === 'Custom'")
    assert page.locator("#volume-preset").input_value() == "Custom"
    clear = canvas(page, artifacts / "volume-tf-clear.png")
    assert np.abs(around(clear, middle) - around(before, middle)).max() < 12

    lo, hi = page.evaluate(
        "() => [window.__miss.transfer.range[0], window.__miss.transfer.range[1]]"
    )
    box = page.locator("#tf-canvas").bounding_box()
    page.mouse.dblclick(
        box["x"] + (700 - lo) / (hi - lo) * box["width"], box["y"] + 0.1 * box["height"]
    )
    page.wait_for_function(f"() => window.__miss.transfer.points.length === {count + 1}")
    page.locator("#tf-colour").fill("#00ff00")
    page.wait_for_function(
        "() => window.__miss.transfer.points.some((p) => p[2] === 1 && p[1] === 0)"
    )
    page.wait_for_function("() => window.__miss.volume.level !== undefined")
    green = around(canvas(page, artifacts / "volume-tf-green.png"), middle)
    assert green[1] > green[0] + 40 and green[1] > green[2] + 40, green
    assert "opacity" in page.inner_text("#tf-note")
    page.screenshot(path=artifacts / "volume-tf-page.png")


def test_the_full_resolution_is_fetched_when_asked(
    page: Any, server: Any, tmp_path: Path, artifacts: Path
) -> None:
    """Issue 43: the first picture comes from a coarse level (no side over 256 voxels); a
    click on "Full resolution" fetches level 1 and draws it in its place, the preset kept;
    a scan whose first level is whole offers no such button."""
    nib = pytest.importorskip("nibabel")
    data = np.full((320, 40, 40), -1000, dtype=np.int16)
    data[100:220, 10:30, 10:30] = 700
    nib.save(nib.Nifti1Image(data, np.diag([0.5, 2.0, 2.0, 1.0])), tmp_path / "long.nii.gz")
    response = upload_cube(page, (tmp_path / "long.nii.gz").read_bytes())
    assert response.status == 201, response.text()
    job = server.post(
        "/api/models", {"volume": response.json()["id"], "level": 300, "decimate": "none"}
    )
    assert server.wait_model(job["id"])["status"] == "done"
    page.goto(f"/models/{job['id']}?view=volume")
    page.wait_for_function("() => window.__miss.volume && window.__miss.volume.on")
    assert page.evaluate("() => window.__miss.volume.dims")[0] <= 256
    assert "(a coarse level)" in page.inner_text("#volume-note")
    page.select_option("#volume-preset", "CT soft tissue")
    page.wait_for_function("() => window.__miss.volume.preset === 'CT soft tissue'")
    page.click("#volume-full")
    page.wait_for_function("() => window.__miss.volume.dims[0] === 320")
    assert page.evaluate("() => window.__miss.volume.preset") == "CT soft tissue"
    assert page.inner_text("#volume-note") == "320 × 40 × 40 voxels"
    assert not page.locator("#volume-full").is_visible()
    middle = page.evaluate("() => window.__miss.voxelToScreen([160, 20, 20])")
    shot = canvas(page, artifacts / "volume-full.png")
    assert np.abs(around(shot, middle) - shot[5, 5]).max() > 60  # the block, on the background


def test_the_address_carries_the_preset_and_the_window(
    page: Any, server: Any, cube_scan: bytes
) -> None:
    """A deep link's ?preset= and ?wl=level,window open the scan so; a change is written
    back, and a reload of the address shows it again."""
    response = upload_cube(page, cube_scan)
    assert response.status == 201, response.text()
    job = server.post("/api/models", {"volume": response.json()["id"], "level": 1450})
    assert server.wait_model(job["id"])["status"] == "done"
    page.goto(f"/models/{job['id']}?view=volume&preset=CT%20lung&wl=-400,1300")
    page.wait_for_function("() => window.__miss.volume && window.__miss.volume.on")
    shown = page.evaluate("() => window.__miss.volume")
    assert (shown["preset"], shown["level"], shown["window"]) == ("CT lung", -400, 1300)
    assert page.locator("#volume-preset").input_value() == "CT lung"
    assert page.locator("#volume-level").input_value() == "-400"

    page.select_option("#volume-preset", "MIP")
    page.wait_for_function("() => new URLSearchParams(location.search).get('preset') === 'MIP'")
    page.fill("#volume-level", "250")
    page.wait_for_function(
        "() => (new URLSearchParams(location.search).get('wl') || '').startsWith('250,')"
    )
    page.reload()
    page.wait_for_function("() => window.__miss.volume && window.__miss.volume.on")
    shown = page.evaluate("() => window.__miss.volume")
    assert (shown["preset"], shown["level"]) == ("MIP", 250)
    page.click("#volume-toggle")
    page.wait_for_function("() => !window.__miss.volume.on")
    page.wait_for_function("() => !/[?&](preset|wl|view)=/.test(location.search)")
