"""The library page takes scans as they arrive: several DICOM slices picked at once, a
MetaImage header with its data file, a zip of two series (asks which), and an unreadable
file (one plain sentence, the reader's finding behind "More")."""

from __future__ import annotations

import os
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import SimpleITK as sitk

REPO = Path(__file__).resolve().parents[2]
DATASETS = Path(os.environ.get("MISS_DATASETS", REPO.parent / "shared" / "datasets"))
GE = DATASETS / "ct_head_dicom_ge_gantrytilt"
MR = DATASETS / "mr_head_dicom_vsseg001_t1"


@pytest.fixture
def page(browser: Any, server: Any, logged_in: Any) -> Iterator[Any]:
    """A laptop-sized page, logged in, whose script errors fail the test. Unlike the
    shared ``page``, the console's "failed to load resource" for the 409 and 422 these
    tests expect is no failure: it is how the page hears the question or the refusal."""
    context = browser.new_context(viewport={"width": 1366, "height": 768}, base_url=server.url)
    logged_in(context)
    opened = context.new_page()
    errors: list[str] = []
    opened.on("pageerror", lambda exc: errors.append(f"page error: {exc}"))
    opened.set_default_timeout(30_000)
    try:
        yield opened
    finally:
        context.close()
    assert not errors, "the page logged errors:\n" + "\n".join(errors)


def card_ids(page: Any) -> set[str]:
    return set(page.eval_on_selector_all(".volume-card", "cards => cards.map(c => c.dataset.id)"))


def pick(page: Any, files: list[Path]) -> None:
    """Choose ``files`` in the library's file picker, as a person selecting several does."""
    page.goto("/")
    page.wait_for_selector("body[data-ready='1']")
    page.set_input_files("#file-input", [str(p) for p in files])


def new_card(page: Any, known: set[str]) -> str:
    """The id of the volume the upload added (waits for the bar to say done)."""
    page.wait_for_selector("#upload-progress[data-done]", timeout=90_000)
    (volume_id,) = card_ids(page) - known
    return volume_id


@pytest.mark.skipif(not GE.is_dir(), reason="needs ../shared/datasets")
def test_several_dicom_files_picked_make_one_volume(page: Any, artifacts: Path) -> None:
    page.goto("/")
    page.wait_for_selector("body[data-ready='1']")
    known = card_ids(page)
    pick(page, sorted(GE.glob("*.dcm"))[:6])
    assert page.inner_text("#upload-name") == "01.dcm and others (6 files)"
    volume_id = new_card(page, known)
    assert page.is_hidden("#upload-error")
    page.screenshot(path=artifacts / "library-after-several-dcm.png")
    page.click(f".volume-card[data-id='{volume_id}'] a.name")
    page.wait_for_url(f"**/volumes/{volume_id}")
    page.wait_for_function(
        "() => document.getElementById('volume-meta').textContent.includes('CT')"
    )
    assert page.inner_text("#volume-meta").startswith("CT · 512 × 512 × ")


def test_metaimage_header_and_data_picked_together(page: Any, server: Any, tmp_path: Path) -> None:
    voxels = np.arange(6 * 5 * 4, dtype=np.int16).reshape(4, 5, 6)
    sitk.WriteImage(sitk.GetImageFromArray(voxels), str(tmp_path / "block.mhd"))
    page.goto("/")
    page.wait_for_selector("body[data-ready='1']")
    known = card_ids(page)
    pick(page, [tmp_path / "block.mhd", tmp_path / "block.raw"])
    volume_id = new_card(page, known)
    assert server.get(f"/api/volumes/{volume_id}")["dims"] == [6, 5, 4]


@pytest.mark.skipif(not (GE.is_dir() and MR.is_dir()), reason="needs ../shared/datasets")
def test_zip_of_two_series_asks_which_and_reads_it(
    page: Any, server: Any, tmp_path: Path, artifacts: Path
) -> None:
    archive = tmp_path / "two-series.zip"
    with zipfile.ZipFile(archive, "w") as zf:
        for p in sorted(GE.glob("*.dcm"))[:3]:
            zf.write(p, f"ct/{p.name}")
        for p in sorted(MR.glob("*.dcm"))[:4]:
            zf.write(p, f"mr/{p.name}")
    page.goto("/")
    page.wait_for_selector("body[data-ready='1']")
    known = card_ids(page)
    pick(page, [archive])
    legend = page.wait_for_selector("#upload-choice legend", timeout=90_000)
    assert legend.inner_text() == "two-series.zip holds 2 series: which one should MISS read?"
    options = page.locator("#upload-choice .series-option")
    texts = [options.nth(i).inner_text() for i in range(options.count())]
    assert texts == [
        "MR · t1_mpr_tra_gk_v4 · 4 slices · 512 × 512",
        "CT · (no description) · 3 slices · 512 × 512",
    ]
    page.screenshot(path=artifacts / "library-choose-series.png")
    options.nth(1).click()  # the CT, not the largest
    page.click("text=Read this series")
    volume_id = new_card(page, known)
    assert page.is_hidden("#upload-choice")
    volume = server.get(f"/api/volumes/{volume_id}")
    assert volume["modality"] == "CT" and volume["units"] == "HU"


def test_unreadable_file_says_one_plain_sentence(
    page: Any, tmp_path: Path, artifacts: Path
) -> None:
    notes = tmp_path / "notes.nii.gz"
    notes.write_bytes(b"hello, these are my notes\n" * 40)
    pick(page, [notes])
    error = page.wait_for_selector("#upload-error:not([hidden])", timeout=90_000)
    plain = page.inner_text("#upload-error .plain")
    assert plain == (
        "notes.nii.gz: not a NIfTI file; check it was not renamed from another format or damaged."
    )
    technical = page.locator("#upload-error .technical")
    assert not technical.is_visible()  # behind "More"
    page.click("#upload-error summary")
    assert "magic at byte 344" in technical.inner_text()
    assert error.inner_text().count("notes.nii.gz") == 2  # once plainly, once in the finding
    page.screenshot(path=artifacts / "library-unreadable-more.png")


#: What the pages say of the GE head CT (gantry tilt 18.5 deg, 28 slices 1.08-7.00 mm apart).
TILT_SAID = (
    "The scanner's gantry was tilted 18.5°: each slice was placed at its true slant, its "
    "pixels unchanged.",
    "The gaps between slices were uneven (1.08 to 7.00 mm): the 28 slices were blended into "
    "38 evenly spaced slices, 3.894 mm apart.",
    "Spacing as used: 0.488 × 0.488 × 3.894 mm (across × down × between slices; 4.106 mm "
    "along the tilted stack).",
)
#: Words of the readers' notes that mean nothing to a physician.
INTERNAL = ("affine", "interpolation", "normal", "median", "deg ")


def read_notes(page: Any) -> str:
    """The text of the volume's notes as shown (they are open: nothing to click)."""
    shown = page.locator("#volume-notes")
    shown.locator("li").first.wait_for(state="visible")
    return str(shown.inner_text())


def assert_said_plainly(said: str, where: str) -> None:
    assert said.startswith("What MISS changed in reading the scan (2)"), (where, said)
    for line in TILT_SAID:
        assert line in said, (where, line, said)
    assert not [w for w in INTERNAL if w in said], (where, said)


def shoot_both_sizes(page: Any, path: Path, name: str) -> None:
    """Screenshots of the notes at a laptop's size and a phone's (scrolled into view)."""
    for width, height in ((1366, 768), (390, 844)):
        page.set_viewport_size({"width": width, "height": height})
        page.locator("#volume-notes").scroll_into_view_if_needed()
        page.screenshot(path=path / f"{name}-notes-{width}.png")
    page.set_viewport_size({"width": 1366, "height": 768})


def axe_violations(
    browser: Any, server: Any, logged_in: Any, url: str, artifacts: Path
) -> list[str]:
    """axe-core's serious violations on ``url`` with its notes shown, at both sizes (in a
    context that lets axe's script past the page's CSP, as test_accessibility does)."""
    from test_accessibility import violations  # skips when axe-core is not installed

    found = []
    for width, height in ((1366, 768), (390, 844)):
        context = browser.new_context(
            viewport={"width": width, "height": height}, base_url=server.url, bypass_csp=True
        )
        logged_in(context)
        opened = context.new_page()
        opened.goto(url)
        read_notes(opened)
        name = url.strip("/").split("/")[0]
        found += violations(opened, f"{name}-notes-{width}", artifacts)
        context.close()
    return found


@pytest.mark.skipif(not GE.is_dir(), reason="needs ../shared/datasets")
def test_what_miss_changed_in_a_tilted_scan_is_shown(
    page: Any, server: Any, browser: Any, logged_in: Any, artifacts: Path
) -> None:
    """Issue 42: a gantry tilt of 18.5 deg and 28 uneven slices resampled onto 38 were
    never shown plainly (the header's 4.106 mm read as the slice gap). The volume page (at
    the top of its side panel), the model page and a share link's page say what MISS
    changed, in plain words, and the spacing as used."""
    page.goto("/")
    page.wait_for_selector("body[data-ready='1']")
    known = card_ids(page)
    pick(page, sorted(GE.glob("*.dcm")))
    volume_id = new_card(page, known)
    page.goto(f"/volumes/{volume_id}")
    page.wait_for_selector("body[data-ready='1']")
    assert_said_plainly(read_notes(page), "volume page")
    assert (
        page.inner_text("#volume-meta") == "CT · 512 × 512 × 38 voxels · 0.488 × 0.488 × 3.894 mm"
    )
    first = page.eval_on_selector(".side", "side => side.firstElementChild.id")
    assert first == "volume-notes"  # beside the volume's details, above the settings
    shoot_both_sizes(page, artifacts, "volume")
    assert axe_violations(browser, server, logged_in, f"/volumes/{volume_id}", artifacts) == []
    model = server.submit(volume_id, level=300, sample_rate=4)
    server.wait_model(model)
    page.goto(f"/models/{model}")
    assert_said_plainly(read_notes(page), "model page")
    shoot_both_sizes(page, artifacts, "model")
    assert axe_violations(browser, server, logged_in, f"/models/{model}", artifacts) == []
    link = server.post("/api/shares", {"model": model})["url"]
    page.goto(link)
    assert_said_plainly(read_notes(page), "share page")
