"""The volume page as a clinician first meets it: a level that fits the scan, named for
what it measures, Generate in sight, and the job's stage shown while the model is made.

Real scans from ../shared/datasets uploaded to the session's ``miss serve``; read as a
person reads the page: text, positions, what is on screen.
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path
from typing import Any

import pytest
from support import ADMIN_PASSWORD, DATASETS

PHONE = {"width": 390, "height": 844}
#: Every text the job's progress shows (the overlay, then the label over the preview),
#: recorded as it changes: the swap to the model's page keeps this document.
RECORD = """() => {
    window.__shown = [];
    const note = () => {
        for (const id of ['building', 'overlay-title', 'overlay-text']) {
            const el = document.getElementById(id);
            const box = el && el.closest('[hidden]') === null ? el.textContent : '';
            if (box && window.__shown[window.__shown.length - 1] !== box) window.__shown.push(box);
        }
    };
    new MutationObserver(note).observe(document.documentElement,
        {subtree: true, childList: true, characterData: true, attributes: true});
}"""


def upload(server: Any, name: str, content: bytes) -> dict[str, Any]:
    r = server.http.post("/api/volumes", files={"file": (name, content)})
    assert r.status_code == 201, r.text
    return dict(r.json())


def zipped(folder: Path) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for file in sorted(folder.iterdir()):
            zf.write(file, f"series/{file.name}")
    return buf.getvalue()


@pytest.fixture(scope="module")
def scans(server: Any) -> dict[str, dict[str, Any]]:
    """A skull-stripped MR (NIfTI: no modality), a DICOM MR and a DICOM CT in HU."""
    if not (DATASETS / "README.md").is_file():
        pytest.skip(f"real scans not found at {DATASETS}")
    gd = DATASETS / "nifti" / "MR_Gd.nii.gz"
    return {
        "mr_nifti": upload(server, gd.name, gd.read_bytes()),
        "mr_dicom": upload(server, "mr.zip", zipped(DATASETS / "mr_forearm_dicom_cptac_sar")),
        "ct": upload(server, "ct.zip", zipped(DATASETS / "ct_head_dicom_ge_gantrytilt")),
    }


def open_volume(page: Any, volume: dict[str, Any]) -> None:
    page.goto(f"/volumes/{volume['id']}")
    page.wait_for_selector("body[data-ready='1']")


def level_label(page: Any) -> str:
    """The name on the level's field, as a person reads it."""
    return str(page.inner_text("label.field:has(#threshold) > span"))


def in_view(page: Any, selector: str) -> bool:
    box = page.locator(selector).bounding_box()
    size = page.viewport_size
    return bool(
        box
        and box["x"] >= 0
        and box["y"] >= 0
        and box["x"] + box["width"] <= size["width"]
        and box["y"] + box["height"] <= size["height"]
    )


@pytest.mark.parametrize("which", ["mr_nifti", "mr_dicom"])
def test_an_mr_opens_on_an_intensity_never_on_bone(
    page: Any, scans: dict[str, dict[str, Any]], which: str, artifacts: Path
) -> None:
    volume = scans[which]
    open_volume(page, volume)
    assert level_label(page) == "Intensity"
    buttons = page.eval_on_selector_all("#presets button", "bs => bs.map(b => b.textContent)")
    assert not [b for b in buttons if "bone" in b], buttons
    first = volume["presets"][0]
    assert first["name"] == "skin"
    assert float(page.input_value("#threshold")) == first["level"]
    assert page.get_attribute("#presets [data-preset=skin]", "aria-pressed") == "true"
    page.screenshot(path=artifacts / f"volume-defaults-{which}.png")


def test_ct_in_hu_keeps_density_and_bone(page: Any, scans: dict[str, dict[str, Any]]) -> None:
    open_volume(page, scans["ct"])
    assert level_label(page) == "Density (HU)"
    assert float(page.input_value("#threshold")) == 300
    assert page.get_attribute("#presets [data-preset=bone]", "aria-pressed") == "true"


def test_generate_is_in_sight_on_a_laptop_and_reachable_on_a_phone(
    page: Any, browser: Any, server: Any, scans: dict[str, dict[str, Any]], artifacts: Path
) -> None:
    open_volume(page, scans["mr_nifti"])
    assert page.viewport_size == {"width": 1366, "height": 768}
    assert in_view(page, "#generate")  # on load, nothing scrolled
    page.screenshot(path=artifacts / "volume-generate-laptop.png")

    context = browser.new_context(viewport=PHONE, base_url=server.url)
    try:
        context.request.post(
            "/api/auth/login", data={"username": "admin", "password": ADMIN_PASSWORD}
        )
        phone = context.new_page()
        open_volume(phone, scans["mr_nifti"])
        phone.locator("#threshold").scroll_into_view_if_needed()
        # beside the level, without scrolling on to the form's foot
        assert in_view(phone, "#threshold") and in_view(phone, "#generate")
        phone.screenshot(path=artifacts / "volume-generate-phone.png")
    finally:
        context.close()


def test_the_page_shows_the_jobs_stage_while_the_model_is_made(
    page: Any, server: Any, scans: dict[str, dict[str, Any]], artifacts: Path
) -> None:
    open_volume(page, scans["mr_nifti"])
    page.evaluate(RECORD)
    page.click("#generate")
    page.wait_for_url("**/models/*")
    model_id = page.url.rstrip("/").split("/")[-1].split("?")[0]
    assert server.wait_model(model_id)["status"] == "done"
    shown = page.evaluate("() => window.__shown")
    stages = [text for text in shown if "Decimation" in text]
    assert stages, shown
    assert any("%" in text for text in stages), stages
    page.screenshot(path=artifacts / "volume-job-done.png")


def test_slice_steps_are_smoothed_by_default_where_slices_are_far_apart(
    page: Any, server: Any, artifacts: Path
) -> None:
    """Issue 42: a scan whose slices are far apart for its pixels (here 0.5 x 0.5 x 2 mm)
    opens with "Smooth slice steps" on, the hint naming both spacings; the model made says
    how far smoothing moved its surface beside the bound. A scan of nearly cubic voxels
    (the demo, 1.5 mm) opens with it off."""
    nib = pytest.importorskip("nibabel")
    import numpy as np

    grid = np.indices((64, 64, 24)).astype(np.float32)
    inside = ((grid[0] - 32) * 0.5) ** 2 + ((grid[1] - 32) * 0.5) ** 2 + ((grid[2] - 12) * 2) ** 2
    data = np.where(inside < 12.0**2, 1000, 0).astype(np.int16)
    image = nib.Nifti1Image(data, np.diag([0.5, 0.5, 2.0, 1.0]))
    volume = upload(server, "steps.nii", image.to_bytes())
    demo = next(v for v in server.http.get("/api/volumes").json() if "emo" in v["name"])
    open_volume(page, demo)
    assert not page.is_checked("#smooth-steps")
    assert "no steps" in page.inner_text("#smooth-hint")
    open_volume(page, volume)
    assert page.is_checked("#smooth-steps")
    hint = page.inner_text("#smooth-hint")
    assert "Slices 2 mm apart, pixels 0.5 mm" in hint, hint
    page.fill("#threshold", "500")
    page.click("#generate")
    page.wait_for_url("**/models/*")
    model_id = page.url.rstrip("/").split("/")[-1].split("?")[0]
    model = server.wait_model(model_id)
    assert model["status"] == "done" and model["params"].get("smooth") == 15, model["params"]
    part = model["stats"]["parts"][0]
    assert 0 < part["smoothing_mean_mm"] < part["smoothing_max_mm"] < 2.0, part
    stats = page.locator("#stats")
    stats.get_by_text("Smoothing moved the surface").wait_for()
    assert f"{part['smoothing_max_mm']:.3f} mm" in stats.inner_text()
    page.screenshot(path=artifacts / "volume-smoothed-model.png")
