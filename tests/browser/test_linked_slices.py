"""Issue 43, linked slices: axial, coronal and sagittal views beside the 3-D view.

A synthetic CT (HU, spacing 2 x 1.5 x 2.5 mm, RAS affine as NIfTI writes it) holds a
700 HU box off the middle in every direction; the model is its surface (level 300). Each
view's outline must lie where the model's own mesh (its STL, patient LPS mm) crosses the
slice's plane, placed on the canvas by radiological orientation (the patient's left on
the screen's right; anterior up in axial, superior up in coronal and sagittal, anterior
on the left in sagittal) over the picture's own rectangle. One crosshair: a click on a
slice moves the other two, a click on the surface in 3-D moves all three, the arrow keys
and the wheel step through slices; ?view=slices opens them.

Screenshots go to test-artifacts/browser/slices-*.png.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh
from PIL import Image

N = 64
SPACING = (2.0, 1.5, 2.5)
BOX = (slice(14, 40), slice(24, 50), slice(30, 56))
# LPS mm of voxel (i, j, k): NIfTI's RAS with x and y negated (the server's frame).
AFFINE = np.diag([-SPACING[0], -SPACING[1], SPACING[2], 1.0])
# Radiological orientation, in LPS: the screen's right and down, and the voxel axis across.
ORIENT = {
    "axial": ((1, 0, 0), (0, 1, 0), 2),
    "coronal": ((1, 0, 0), (0, 0, -1), 1),
    "sagittal": ((0, 1, 0), (0, 0, -1), 0),
}
LABELS = {
    "axial": {"left": "R", "right": "L", "top": "A", "bottom": "P"},
    "coronal": {"left": "R", "right": "L", "top": "S", "bottom": "I"},
    "sagittal": {"left": "A", "right": "P", "top": "S", "bottom": "I"},
}
SHOWN = "() => window.__miss.slices && window.__miss.slices.on"
OUTLINED = (
    "() => window.__miss.ready && window.__miss.slices && window.__miss.slices.on"
    " && window.__miss.slices.views.axial.outlines.some((o) => o.segments.length)"
)


@pytest.fixture(scope="module")
def box_scan(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    nib = pytest.importorskip("nibabel")
    data = np.full((N, N, N), -1000, dtype=np.int16)
    data[BOX] = 700
    path = tmp_path_factory.mktemp("box") / "box.nii.gz"
    nib.save(nib.Nifti1Image(data, np.diag([*SPACING, 1.0])), path)
    return path.read_bytes()


@pytest.fixture(scope="module")
def box_model(browser: Any, server: Any, box_scan: bytes) -> dict[str, Any]:
    """The box's surface at 300 HU, undecimated: {id, mesh (trimesh, LPS mm)}."""
    from conftest import laptop_page

    with laptop_page(browser, server) as page:
        job = box_surface(page, server, box_scan)
    stl = server.http.get(f"/api/models/{job['id']}/model.stl")
    assert stl.status_code == 200, stl.text
    mesh = trimesh.load(io.BytesIO(stl.content), file_type="stl", process=False)
    return {"id": job["id"], "mesh": mesh}


def box_surface(page: Any, server: Any, box_scan: bytes, level: int = 300) -> dict[str, Any]:
    """The box scan uploaded through the page's session, and its surface at ``level`` HU
    made (a level of its own is a model, and a room, of its own)."""
    csrf = next(c["value"] for c in page.context.cookies() if c["name"] == "miss_csrf")
    file = {"name": "box.nii.gz", "mimeType": "application/gzip", "buffer": box_scan}
    response = page.request.post(
        "/api/volumes", headers={"X-CSRF-Token": csrf}, multipart={"file": file}
    )
    assert response.status == 201, response.text()
    body = {"volume": response.json()["id"], "level": level, "decimate": "none"}
    job = server.post("/api/models", body)
    assert server.wait_model(job["id"])["status"] == "done"
    return job


def to_canvas(view: dict[str, Any], name: str, lps: np.ndarray) -> np.ndarray:
    """LPS mm points (n, 3) -> the view's canvas CSS px (n, 2): radiological orientation
    over the picture's rectangle, which spans the grid's voxels edge to edge."""
    right, down, _ = ORIENT[name]
    corners = np.array(
        [[i, j, k, 1] for i in (-0.5, N - 0.5) for j in (-0.5, N - 0.5) for k in (-0.5, N - 0.5)]
    )
    corners = (corners @ AFFINE.T)[:, :3]
    x0, y0, w, h = view["rect"]
    out = []
    for axis, origin, size in ((right, x0, w), (down, y0, h)):
        along = corners @ np.array(axis, float)
        out.append(origin + (lps @ np.array(axis, float) - along.min()) / np.ptp(along) * size)
    return np.stack(out, axis=1)


def expected_segments(mesh: Any, view: dict[str, Any], name: str) -> np.ndarray:
    """The mesh's own crossing of the view's slice plane (trimesh), in canvas px (n, 4)."""
    axis = ORIENT[name][2]
    normal = AFFINE[:3, axis] / np.linalg.norm(AFFINE[:3, axis])
    origin = AFFINE[:3, axis] * view["index"]
    lines = trimesh.intersections.mesh_plane(mesh, normal, origin)
    ends = to_canvas(view, name, lines.reshape(-1, 3)).reshape(-1, 2, 2)
    return ends.reshape(-1, 4)


def samples(segments: np.ndarray, step: float = 0.5) -> np.ndarray:
    """Points every ``step`` px along segments (n, 4) -> (m, 2)."""
    points = []
    for x0, y0, x1, y1 in segments:
        n = max(2, int(np.hypot(x1 - x0, y1 - y0) / step) + 1)
        t = np.linspace(0, 1, n)[:, None]
        points.append(np.array([x0, y0]) + t * np.array([x1 - x0, y1 - y0]))
    return np.concatenate(points)


def farthest(a: np.ndarray, b: np.ndarray) -> float:
    """The largest distance from a point of ``a`` to the nearest point of ``b`` (px)."""
    return float(np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)).min(axis=1).max())


def rgb(hex_colour: str) -> np.ndarray:
    return np.array([int(hex_colour[i : i + 2], 16) for i in (1, 3, 5)])


def on_outline(image: np.ndarray, segments: np.ndarray, colour: np.ndarray) -> bool:
    """Whether the middles of the four longest segments show ``colour`` (within a px)."""
    longest = sorted(segments, key=lambda s: -np.hypot(s[2] - s[0], s[3] - s[1]))[:4]
    for x0, y0, x1, y1 in longest:
        x, y = round((x0 + x1) / 2), round((y0 + y1) / 2)
        near = image[y - 1 : y + 2, x - 1 : x + 2].reshape(-1, 3)
        if np.abs(near - colour).max(axis=1).min() >= 40:
            return False
    return True


def view_image(page: Any, name: str, path: Path) -> np.ndarray:
    page.evaluate("() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))")
    shot = page.locator(f'.slice-view[data-view="{name}"] canvas').screenshot()
    path.write_bytes(shot)
    return np.asarray(Image.open(io.BytesIO(shot)).convert("RGB"), dtype=np.int16)


def test_outlines_lie_where_the_mesh_crosses_each_slice(
    page: Any, box_model: dict[str, Any], artifacts: Path
) -> None:
    page.goto(f"/models/{box_model['id']}?view=slices")
    page.wait_for_function(OUTLINED)
    state = page.evaluate("() => window.__miss.slices")
    np.testing.assert_allclose(np.array(state["affine"]), AFFINE, atol=1e-6)
    page.screenshot(path=str(artifacts / "slices-laptop.png"))
    swatch = page.locator("[data-role=color]").first
    colour = rgb(swatch.input_value())  # the part's colour as the structures list shows it
    for name, view in state["views"].items():
        assert view["labels"] == LABELS[name]
        assert page.locator(f'.slice-view[data-view="{name}"] .readout').inner_text() == (
            f"{name} {view['index'] + 1} / {N}"
        )
        right, down, _ = ORIENT[name]
        mm = [N * SPACING[int(np.flatnonzero(d)[0])] for d in (right, down)]  # diagonal affine
        assert abs(view["rect"][2] / view["rect"][3] - mm[0] / mm[1]) < 0.02  # true aspect
        drawn = np.array([s for o in view["outlines"] for s in o["segments"]])
        expected = expected_segments(box_model["mesh"], view, name)
        assert len(drawn) and len(expected), name
        assert farthest(samples(drawn), samples(expected)) < 1.0, name
        assert farthest(samples(expected), samples(drawn)) < 1.0, name
        # What shows: the surface's colour on the outline, the box's grey inside it.
        image = view_image(page, name, artifacts / f"slices-{name}.png")
        assert on_outline(image, expected, colour), name
        x0, y0, w, h = (round(v) for v in view["rect"])
        picture = image[y0 : y0 + h, x0 : x0 + w]  # not the edge labels about it
        grey = (picture.min(axis=2) > 60) & (np.ptp(picture, axis=2) < 20)
        ys, xs = np.nonzero(grey)
        xs, ys = xs + x0, ys + y0
        # The box's voxels fill the outline: their grey reaches it on every side (the 2-px
        # line itself covers the grey's last pixel or two).
        box = samples(expected)
        for edge, found in (
            (box[:, 0].min(), xs.min()),
            (box[:, 0].max(), xs.max()),
            (box[:, 1].min(), ys.min()),
            (box[:, 1].max(), ys.max()),
        ):
            assert abs(found - edge) < 4, (name, found, edge)

    # Another colour in the list: the outlines follow; the part hidden: none.
    swatch.fill("#00ff00")
    page.wait_for_function(
        "() => window.__miss.slices.views.axial.outlines[0].colour === '#00ff00'"
    )
    axial = page.evaluate("() => window.__miss.slices.views.axial")
    image = view_image(page, "axial", artifacts / "slices-axial-green.png")
    assert on_outline(image, expected_segments(box_model["mesh"], axial, "axial"), rgb("#00ff00"))


def test_hidden_parts_and_the_volumes_window(
    page: Any, server: Any, box_scan: bytes, artifacts: Path
) -> None:
    """A hidden part has no outline; the slices take the volume's window (the lung
    window shows the 700 HU box white) and the address keeps both views."""
    job = box_surface(page, server, box_scan)  # a scan of its own: the room keeps the view
    page.goto(f"/models/{job['id']}?view=slices")
    page.wait_for_function(OUTLINED)
    page.locator("[data-role=visible]").first.uncheck()
    page.wait_for_function("() => !window.__miss.slices.views.axial.outlines.length")
    page.locator("[data-role=visible]").first.check()
    page.wait_for_function(OUTLINED)

    page.click("#volume-toggle")
    page.wait_for_function("() => window.__miss.volume && window.__miss.volume.on")
    views = page.evaluate("() => new URL(location.href).searchParams.get('view')")
    assert set(views.split(",")) == {"volume", "slices"}
    axial = page.evaluate("() => window.__miss.slices.views.axial")
    inside = to_canvas(axial, "axial", np.array([[-40.0, -65.0, 80.0]]))[0]  # in the box
    image = view_image(page, "axial", artifacts / "slices-bone-window.png")
    assert 100 < image[round(inside[1]), round(inside[0])].mean() < 160  # bone: 700 HU mid-grey
    page.select_option("#volume-preset", "CT lung")
    page.wait_for_function("() => window.__miss.slices.window[0] === -600")
    image = view_image(page, "axial", artifacts / "slices-lung-window.png")
    assert image[round(inside[1]), round(inside[0])].min() > 240  # lung: 700 HU white


def test_a_click_on_a_slice_moves_the_other_two(page: Any, box_model: dict[str, Any]) -> None:
    page.goto(f"/models/{box_model['id']}?view=slices")
    page.wait_for_function(OUTLINED)
    before = page.evaluate("() => window.__miss.slices")
    axial = before["views"]["axial"]
    # On the axial slice's plane (the crosshair leaves the scan's middle, between two).
    target = np.array([[-40.0, -60.0, SPACING[2] * axial["index"]]])
    x, y = to_canvas(axial, "axial", target)[0]
    box = page.locator('.slice-view[data-view="axial"] canvas').bounding_box()
    page.mouse.click(box["x"] + x, box["y"] + y)
    page.wait_for_function(
        "() => window.__miss.slices.views.coronal.index === 40"
        " && window.__miss.slices.views.sagittal.index === 20"
    )
    after = page.evaluate("() => window.__miss.slices")
    np.testing.assert_allclose(after["point"], target[0], atol=0.8)  # within a pixel's mm
    assert after["views"]["axial"]["index"] == axial["index"]
    readout = page.locator('.slice-view[data-view="coronal"] .readout').inner_text()
    assert readout == f"coronal 41 / {N}"


def test_a_click_on_the_surface_moves_all_three(
    page: Any, box_model: dict[str, Any], artifacts: Path
) -> None:
    page.goto(f"/models/{box_model['id']}?view=slices")
    page.wait_for_function(OUTLINED)
    # A point on the box's anterior face (j = 49.24 where 700 HU falls to 300 HU), which
    # the opening view (the patient facing us) shows.
    face = -SPACING[1] * (49 + (700 - 300) / 1700)
    target = [-36.0, face, 100.0]
    x, y = page.evaluate(f"() => window.__miss.lpsToScreen({target})")
    page.mouse.click(x, y)
    page.wait_for_function("() => window.__miss.slices.views.axial.index === 40")
    after = page.evaluate("() => window.__miss.slices")
    np.testing.assert_allclose(after["point"], target, atol=1.0)
    assert after["views"]["coronal"]["index"] == 49 and after["views"]["sagittal"]["index"] == 18
    page.evaluate("() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))")
    shot = page.locator("#stage canvas").screenshot()
    (artifacts / "slices-marker.png").write_bytes(shot)
    image = np.asarray(Image.open(io.BytesIO(shot)).convert("RGB"), dtype=np.int16)
    stage = page.locator("#stage canvas").bounding_box()
    cx, cy = round(x - stage["x"]), round(y - stage["y"])
    marker = image[cy - 1 : cy + 2, cx - 1 : cx + 2].reshape(-1, 3).mean(axis=0)
    assert marker[0] > 200 and marker[1] > 170 and marker[2] < 80, marker  # the yellow marker


def test_keys_and_wheel_step_slices_and_the_address_keeps_the_view(
    page: Any, server: Any, box_scan: bytes
) -> None:
    # Its own model: the others' rooms keep the slices their tests left open.
    job = box_surface(page, server, box_scan, level=290)
    page.goto(f"/models/{job['id']}")
    page.wait_for_function("() => window.__miss.ready === true")
    assert not page.locator("#slices").is_visible()
    page.click("#slices-toggle")
    page.wait_for_function(OUTLINED)
    assert "view=slices" in page.url
    start = page.evaluate("() => window.__miss.slices")
    axial = page.get_by_role("slider", name="Axial slice")
    axial.focus()
    page.keyboard.press("ArrowUp")
    page.keyboard.press("ArrowUp")
    k = start["views"]["axial"]["index"] + 2
    page.wait_for_function(f"() => window.__miss.slices.views.axial.index === {k}")
    point = page.evaluate("() => window.__miss.slices.point")
    assert abs(point[2] - SPACING[2] * k) < 1e-6  # the crosshair moved with the slice
    assert axial.get_attribute("aria-valuetext") == f"axial {k + 1} / {N}"
    page.keyboard.press("PageDown")
    page.wait_for_function(f"() => window.__miss.slices.views.axial.index === {k - 10}")
    sagittal = page.locator('.slice-view[data-view="sagittal"] canvas').bounding_box()
    page.mouse.move(sagittal["x"] + 40, sagittal["y"] + 40)
    i = start["views"]["sagittal"]["index"]
    page.mouse.wheel(0, 100)
    page.wait_for_function(f"() => window.__miss.slices.views.sagittal.index === {i + 1}")

    here = page.evaluate("() => window.__miss.slices.point")
    address = "() => (new URLSearchParams(location.search).get('at') || '').split(',').map(Number)"
    page.wait_for_function(
        f"(p) => ({address})().every((x, n) => Math.abs(x - p[n]) <= 0.051)", arg=here
    )

    page.reload()  # the address opens the slices again, at the same crosshair
    page.wait_for_function("() => window.__miss.ready && window.__miss.slices?.views")
    assert page.locator("#slices-toggle").get_attribute("aria-pressed") == "true"
    views = page.evaluate("() => window.__miss.slices.views")
    assert views["axial"]["index"] == k - 10 and views["sagittal"]["index"] == i + 1
    np.testing.assert_allclose(page.evaluate("() => window.__miss.slices.point"), here, atol=0.05)
    page.click("#slices-toggle")
    page.wait_for_function("() => !window.__miss.slices.on")
    assert "view=" not in page.url and "at=" not in page.url
    assert not page.locator("#slices").is_visible()


def test_the_slices_fit_a_phone(
    browser: Any, server: Any, box_model: dict[str, Any], artifacts: Path
) -> None:
    from conftest import log_in_context

    context = browser.new_context(viewport={"width": 390, "height": 844}, base_url=server.url)
    try:
        log_in_context(context)
        phone = context.new_page()
        phone.goto(f"/models/{box_model['id']}?view=slices")
        phone.wait_for_function(OUTLINED)
        phone.screenshot(path=str(artifacts / "slices-phone.png"))
        stage = phone.locator("#stage").bounding_box()
        for name in ORIENT:
            box = phone.locator(f'.slice-view[data-view="{name}"] canvas').bounding_box()
            assert box["x"] >= 0 and box["x"] + box["width"] <= 390, name
            assert box["width"] > 100 and box["height"] > 100, name
            assert box["y"] >= stage["y"] + stage["height"] - 1, name  # under the 3-D view
            assert box["y"] + box["height"] <= 844, name  # seen without scrolling
    finally:
        context.close()


def test_a_link_that_offers_the_scan_opens_the_slices(
    browser: Any, server: Any, box_model: dict[str, Any]
) -> None:
    """A guest's page draws the slices from /s/{token}/voxels; a plain link has none."""
    from conftest import LAPTOP

    plain = server.post("/api/shares", {"model": box_model["id"], "expires_in": 3600})
    scan = server.post(
        "/api/shares", {"model": box_model["id"], "expires_in": 3600, "can_view_volume": True}
    )
    context = browser.new_context(viewport=LAPTOP, base_url=server.url)
    try:
        guest = context.new_page()
        guest.goto(f"{plain['url']}?view=slices")
        guest.wait_for_function("() => window.__miss.ready === true")
        assert not guest.locator("#slices-toggle").is_visible()
        assert not guest.locator("#slices").is_visible()
        guest.goto(f"{scan['url']}?view=slices")
        guest.wait_for_function(OUTLINED)
        assert guest.locator("#slices-toggle").get_attribute("aria-pressed") == "true"
        assert guest.get_by_role("slider", name="Sagittal slice").is_visible()
    finally:
        context.close()


def test_a_room_follows_the_slices_and_the_crosshair(
    page: Any, browser: Any, server: Any, box_scan: bytes, artifacts: Path
) -> None:
    """Rooms follow the crosshair like the camera: the owner opens the slices and clicks a
    point on one, and a guest in the room (a link that offers the scan) gets the slices on,
    the same crosshair and the same slices; a reload gives the owner the view back."""
    from conftest import owner_and_guest

    job = box_surface(page, server, box_scan, level=310)  # a room of its own
    with owner_and_guest(page, browser, server, job["id"]) as guest:
        assert not guest.locator("#slices").is_visible()
        page.click("#slices-toggle")
        page.wait_for_function(OUTLINED)
        guest.wait_for_function(OUTLINED)
        assert guest.locator("#slices-toggle").get_attribute("aria-pressed") == "true"

        axial = page.evaluate("() => window.__miss.slices.views.axial")
        target = np.array([[-40.0, -60.0, SPACING[2] * axial["index"]]])
        x, y = to_canvas(axial, "axial", target)[0]
        box = page.locator('.slice-view[data-view="axial"] canvas').bounding_box()
        page.mouse.click(box["x"] + x, box["y"] + y)
        moved = (
            "() => window.__miss.slices.views.coronal.index === 40"
            " && window.__miss.slices.views.sagittal.index === 20"
        )
        page.wait_for_function(moved)
        guest.wait_for_function(moved)
        mine = page.evaluate("() => window.__miss.slices.point")
        theirs = guest.evaluate("() => window.__miss.slices.point")
        np.testing.assert_allclose(theirs, mine, atol=1e-6)
        assert (
            guest.locator('.slice-view[data-view="coronal"] .readout').inner_text()
            == f"coronal 41 / {N}"
        )
        guest.screenshot(path=artifacts / "slices-room-guest.png")

        page.goto(f"/models/{job['id']}")  # no ?view= in the address: the room's view
        page.wait_for_function(OUTLINED)
        page.wait_for_function(moved)
        np.testing.assert_allclose(
            page.evaluate("() => window.__miss.slices.point"), mine, atol=1e-6
        )


def test_a_share_link_opens_on_the_view_its_owner_sees(
    page: Any, browser: Any, server: Any, box_scan: bytes, artifacts: Path
) -> None:
    """The share dialog's link carries the camera, the slices and their crosshair when the
    link offers the scan; without the scan, the camera alone."""
    from conftest import LAPTOP

    job = box_surface(page, server, box_scan, level=295)
    page.goto(f"/models/{job['id']}?view=slices")
    page.wait_for_function(OUTLINED)
    axial = page.evaluate("() => window.__miss.slices.views.axial")
    target = np.array([[-40.0, -60.0, SPACING[2] * axial["index"]]])
    x, y = to_canvas(axial, "axial", target)[0]
    box = page.locator('.slice-view[data-view="axial"] canvas').bounding_box()
    page.mouse.click(box["x"] + x, box["y"] + y)
    page.wait_for_function("() => /[?&]at=/.test(location.search)")
    here = page.evaluate("() => window.__miss.slices.point")

    def link(scan: bool) -> str:
        page.click("#share")
        page.wait_for_selector("#share-dialog[open]")
        assert page.is_checked("#share-here")
        page.set_checked("#share-volume", scan)
        page.evaluate("() => { document.getElementById('share-url').value = '' }")
        page.click("#share-create")
        page.wait_for_function("() => document.getElementById('share-url').value.includes('/s/')")
        url = page.input_value("#share-url")
        page.screenshot(path=artifacts / f"slices-share-dialog-{'scan' if scan else 'plain'}.png")
        page.click("#share-dialog button:text('Close')")
        return url

    with_scan, plain = link(True), link(False)
    assert "view=slices" in with_scan and "at=" in with_scan
    assert "view=" not in plain and "at=" not in plain
    context = browser.new_context(viewport=LAPTOP)
    try:
        guest = context.new_page()
        guest.goto(with_scan)
        guest.wait_for_function(OUTLINED)
        np.testing.assert_allclose(
            guest.evaluate("() => window.__miss.slices.point"), here, atol=0.06
        )
        guest.goto(plain)
        guest.wait_for_function("() => window.__miss.ready === true")
        assert not guest.locator("#slices").is_visible()
    finally:
        context.close()


def test_outlines_stop_at_the_clipping_plane(
    page: Any, server: Any, box_scan: bytes, artifacts: Path
) -> None:
    """What the 3-D view's clipping plane cuts away has no outline on the slices: an axial
    plane halfway up the model leaves the coronal outline below it only."""
    job = box_surface(page, server, box_scan, level=305)  # its own room: the clip is kept
    stl = server.http.get(f"/api/models/{job['id']}/model.stl")
    mesh = trimesh.load(io.BytesIO(stl.content), file_type="stl", process=False)
    low, high = mesh.bounds[:, 2]
    middle = (low + high) / 2  # the plane at fraction 0.5 of the model's axial extent
    page.goto(f"/models/{job['id']}?view=slices")
    page.wait_for_function(OUTLINED)
    page.wait_for_function("() => window.__miss.slices.views.coronal.outlines[0].segments.length")

    def heights() -> np.ndarray:
        coronal = page.evaluate("() => window.__miss.slices.views.coronal")
        segments = np.array(coronal["outlines"][0]["segments"], float).reshape(-1, 2, 2)
        return segments[:, :, 1].ravel()

    coronal = page.evaluate("() => window.__miss.slices.views.coronal")
    plane_y = to_canvas(coronal, "coronal", np.array([[0.0, 0.0, middle]]))[0][1]
    assert heights().min() < plane_y - 5  # the whole box's outline, over the plane too
    page.select_option("#clip-axis", "axial")
    page.evaluate(
        """([selector, value]) => {
            const input = document.querySelector(selector);
            input.value = String(value);
            input.dispatchEvent(new Event('input', { bubbles: true }));
        }""",
        ["#clip-position", 0.5],
    )
    page.wait_for_function(
        "(y) => window.__miss.slices.views.coronal.outlines[0].segments"
        ".every((s) => s[1] >= y - 1 && s[3] >= y - 1)",
        arg=float(plane_y),
    )
    kept = heights()
    assert kept.min() >= plane_y - 1 and kept.max() > plane_y + 5  # the part below stays
    view_image(page, "coronal", artifacts / "slices-clipped.png")
