"""The volume page's slices as a person uses them before any model exists: a label map's
colours over the grey, the value under the pointer (HU, 1-based place), a click that
moves the other views to that voxel, Ctrl+wheel zoom and right-drag window/level.

A synthetic CT (RAS NIfTI, 40 voxels a side): a ramp of values, so every voxel says
where it is, and a label map with one box. Screenshots: test-artifacts/browser/slices-*.png.
"""

from __future__ import annotations

import io
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

N = 40
BOX = slice(8, 32)  # the labelled box, voxels
AXIAL = ".view[data-axis=axial]"


def ramp() -> np.ndarray:
    """HU = -1000 + 20 i + j + k/2: each voxel's value names it."""
    i, j, k = np.meshgrid(np.arange(N), np.arange(N), np.arange(N), indexing="ij")
    return (-1000 + 20 * i + j + k // 2).astype(np.int16)


@pytest.fixture(scope="module")
def scan(server: Any, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The ramp uploaded as a CT, with a label map (label 1 in BOX) laid over it."""
    nib = pytest.importorskip("nibabel")
    folder = tmp_path_factory.mktemp("slices")
    affine = np.diag([2.0, 2.0, 2.0, 1.0])  # RAS: i runs to the patient's right
    image = nib.Nifti1Image(ramp(), affine)
    image.header["descrip"] = b"CT HU"  # NIfTI has no modality: the description says it
    nib.save(image, folder / "ramp.nii.gz")
    labels = np.zeros((N, N, N), dtype=np.uint8)
    labels[BOX, BOX, BOX] = 1
    nib.save(nib.Nifti1Image(labels, affine), folder / "seg.nii.gz")
    files = {"file": ("ramp.nii.gz", (folder / "ramp.nii.gz").read_bytes())}
    r = server.http.post("/api/volumes", files=files)
    assert r.status_code == 201, r.text
    volume = r.json()
    files = {"file": ("seg.nii.gz", (folder / "seg.nii.gz").read_bytes())}
    r = server.http.post(f"/api/volumes/{volume['id']}/labelmap", files=files)
    assert r.status_code in (200, 201), r.text
    return dict(r.json())


def open_page(page: Any, volume: dict[str, Any]) -> None:
    page.goto(f"/volumes/{volume['id']}")
    page.wait_for_selector("body[data-ready='1']")
    page.wait_for_function(
        f"() => document.querySelector('{AXIAL} img').dataset.loaded?.includes('labels=true')"
    )


def at(page: Any, view: str, fx: float, fy: float) -> tuple[float, float]:
    """The screen point at fractions of a view's picture."""
    box = page.locator(f"{view} .frame").bounding_box()
    return box["x"] + fx * box["width"], box["y"] + fy * box["height"]


def picture(page: Any, view: str, path: Path) -> np.ndarray:
    shot = page.locator(f"{view} .frame").screenshot(path=str(path))
    return np.asarray(Image.open(io.BytesIO(shot)).convert("RGB"), dtype=np.int16)


def probe_text(page: Any) -> str:
    page.wait_for_function(f"() => !/…/.test(document.querySelector('{AXIAL} .probe').textContent)")
    return str(page.inner_text(f"{AXIAL} .probe"))


def test_label_map_colours_the_slices_before_any_model(
    page: Any, scan: dict[str, Any], artifacts: Path
) -> None:
    open_page(page, scan)
    assert "show on the slices" in page.inner_text("#labelmap")
    image = picture(page, AXIAL, artifacts / "slices-labels.png")
    h, w, _ = image.shape
    # right of the middle: low values (the patient's left, low i), under the threshold's tint
    x, y = int(0.68 * w), h // 2
    inside = image[y - 2 : y + 3, x - 2 : x + 3].reshape(-1, 3).mean(0)
    outside = image[h // 12, w - w // 12]
    colour = np.asarray(scan["labelmap"]["labels"][0]["color"]) * 255
    # the label's own colour shows through: the grey's channels are equal, the blend's
    # differ as the colour's do
    assert np.ptp(outside) <= 3
    assert np.sign(np.diff(inside)).tolist() == np.sign(np.diff(colour)).tolist()
    assert np.ptp(inside) > 0.3 * np.ptp(colour)
    page.uncheck("#labelmap .label-overlay input")
    page.wait_for_function(
        f"() => !document.querySelector('{AXIAL} img').dataset.loaded.includes('labels=')"
    )
    plain = picture(page, AXIAL, artifacts / "slices-labels-off.png")
    assert np.ptp(plain[y, x]) <= 3


def test_pointer_reads_the_voxel_value_in_hu_and_its_place(
    page: Any, scan: dict[str, Any], artifacts: Path
) -> None:
    open_page(page, scan)
    assert "right-drag" in page.inner_text("#slice-hint")
    # a quarter across and down the axial view: the patient's right (high i in RAS) and
    # anterior (high j) are on the screen's left and top
    page.mouse.move(*at(page, AXIAL, 10.5 / N, 10.5 / N))
    text = probe_text(page)
    page.screenshot(path=artifacts / "slices-readout.png")
    i, j, k = N - 1 - 10, N - 1 - 10, N // 2
    assert f"i {i + 1}, j {j + 1}, slice {k + 1}" in text
    assert f"{int(ramp()[i, j, k])} HU" in text
    assert "label 1" in text  # inside the box, named as the map names it


def test_click_moves_the_other_views_and_draws_the_cross_hair(
    page: Any, scan: dict[str, Any], artifacts: Path
) -> None:
    open_page(page, scan)
    page.mouse.click(*at(page, AXIAL, 5.5 / N, 30.5 / N))
    i, j = N - 1 - 5, N - 1 - 30
    page.wait_for_function(
        f"() => document.querySelector('.view[data-axis=sagittal] .index').textContent"
        f".startsWith('{i + 1} /')"
    )
    assert page.inner_text(".view[data-axis=coronal] .index").startswith(f"{j + 1} /")
    # the coronal view shows the sagittal slice as a vertical line at i: yellow pixels
    coronal = ".view[data-axis=coronal]"
    image = picture(page, coronal, artifacts / "slices-cross.png")
    h, w, _ = image.shape
    x = round(w * (N - 1 - i + 0.5) / N)
    column = image[:, max(0, x - 2) : x + 3]
    yellow = (column[..., 0] > 150) & (column[..., 1] > 120) & (column[..., 2] < 110)
    assert yellow.any(axis=1).mean() > 0.8


def test_ctrl_wheel_zooms_about_the_pointer_and_right_drag_sets_window_level(
    page: Any, scan: dict[str, Any], artifacts: Path
) -> None:
    open_page(page, scan)
    before = page.locator(f"{AXIAL} .frame").bounding_box()
    point = at(page, AXIAL, 0.3, 0.6)
    page.mouse.move(*point)
    place = probe_text(page).split(" · ")[0]
    page.keyboard.down("Control")
    page.mouse.wheel(0, -200)
    page.keyboard.up("Control")
    page.wait_for_function(f"() => Number(document.querySelector('{AXIAL}').dataset.zoom) > 2")
    after = page.locator(f"{AXIAL} .frame").bounding_box()
    assert after["width"] > 2 * before["width"]
    page.mouse.move(point[0] + 1, point[1])
    page.mouse.move(*point)
    assert probe_text(page).split(" · ")[0] == place  # the same voxel under the pointer
    page.screenshot(path=artifacts / "slices-zoomed.png")

    window = float(page.input_value("#window"))
    page.mouse.down(button="right")
    page.mouse.move(point[0] + 120, point[1], steps=6)
    page.mouse.up(button="right")
    assert float(page.input_value("#window")) > window
    assert page.input_value("#wl-preset") == ""  # custom now
    assert re.search(r"window=([\d.]+)", page.get_attribute(f"{AXIAL} img", "src") or "")


def test_a_tap_on_a_phone_reads_the_voxel_and_moves_the_views(
    browser: Any, server: Any, scan: dict[str, Any], logged_in: Any, artifacts: Path
) -> None:
    """A finger has no hover: the tap's readout stays after it lifts (390x844, touch)."""
    context = browser.new_context(
        viewport={"width": 390, "height": 844}, has_touch=True, is_mobile=True,
        base_url=server.url,
    )  # fmt: skip
    logged_in(context)
    page = context.new_page()
    try:
        open_page(page, scan)
        box = page.locator(f"{AXIAL} .frame").bounding_box()
        middle = {"x": box["width"] * 20.5 / N, "y": box["height"] * 20.5 / N}  # a voxel's centre
        page.tap(f"{AXIAL} .frame", position=middle)
        text = probe_text(page)
        page.screenshot(path=artifacts / "slices-phone-tap.png")
        i, j, k = N - 1 - 20, N - 1 - 20, N // 2
        assert f"i {i + 1}, j {j + 1}, slice {k + 1}" in text
        assert f"{int(ramp()[i, j, k])} HU" in text
        assert page.inner_text(".view[data-axis=sagittal] .index").startswith(f"{i + 1} /")
    finally:
        context.close()
