"""Managing one's work in the pages, as a physician meets it: Cancel a running job on its
page, the volume's list following its jobs to the end (names, dates, plural right),
Rename and Delete a model, a colleague at a model not shared with them, and "Send to
PACS" only where a PACS is configured."""

from __future__ import annotations

import gzip
import re
from pathlib import Path
from typing import Any

import nibabel as nib
import numpy as np
import pytest
from browser.conftest import LAPTOP
from support.realserver import Server


def upload(server: Server, content: bytes, name: str, headers: dict[str, str] | None = None) -> str:
    r = server.http.post("/api/volumes", files={"file": (name, content)}, headers=headers or {})
    assert r.status_code == 201, r.text
    return r.json()["id"]


@pytest.fixture(scope="module")
def noise(server: Server) -> str:
    """A 128³ volume of noise: at level 0 and sample rate 1 its job runs for long (millions
    of triangles to decimate), so it is surely running when the page cancels it."""
    data = np.random.default_rng(0).integers(-1000, 1000, (128, 128, 128)).astype(np.int16)
    image = nib.Nifti1Image(data, np.eye(4))
    return upload(server, gzip.compress(image.to_bytes(), compresslevel=1), "noise.nii.gz")


@pytest.fixture(scope="module")
def head(server: Server, phantom: Path) -> str:
    return upload(server, phantom.read_bytes(), "phantom-head.nii.gz")


def new_page(browser: Any, server: Server, logged_in: Any, *who: str) -> Any:
    context = browser.new_context(viewport=LAPTOP, base_url=server.url)
    logged_in(context, *who)
    page = context.new_page()
    page.set_default_timeout(60_000)
    return page


def entry(page: Any, model_id: str) -> Any:
    """The volume page's entry of the model: the item that links its page."""
    return page.locator(f"#models li:has(a[href='/models/{model_id}'])")


def test_cancel_a_running_job_on_its_page(
    browser: Any, server: Server, noise: str, artifacts: Path, logged_in: Any
) -> None:
    long_job = server.submit(noise, level=0, sample_rate=1)
    model_page = new_page(browser, server, logged_in)
    model_page.goto(f"/models/{long_job}")
    cancel = model_page.locator("#cancel-job")
    cancel.wait_for()
    server.wait(long_job, ("running",))
    assert cancel.inner_text() == "Cancel job"
    model_page.screenshot(path=artifacts / "manage-running.png")
    cancel.click()
    model_page.wait_for_function(
        "() => document.getElementById('overlay-title').textContent === 'Job cancelled'"
    )
    assert "cancelled by admin" in model_page.inner_text("#overlay-text")
    assert not cancel.is_visible()
    model_page.screenshot(path=artifacts / "manage-cancelled.png")
    assert server.model(long_job)["status"] == "failed"
    model_page.context.close()


def test_the_volume_list_follows_its_jobs_to_the_end(
    browser: Any, server: Server, noise: str, head: str, artifacts: Path, logged_in: Any
) -> None:
    long_job = server.submit(noise, level=1, sample_rate=1)
    server.wait(long_job, ("running",))
    # Queued behind it (one worker): it runs once the long one is gone.
    short_job = server.submit(head, level=300, sample_rate=4, decimate="none")
    assert server.model(short_job)["status"] == "queued"
    page = new_page(browser, server, logged_in)
    page.goto(f"/volumes/{head}")
    page.wait_for_selector("body[data-ready='1']")
    entry(page, short_job).wait_for()
    assert "queued" in entry(page, short_job).inner_text()
    assert server.http.delete(f"/api/models/{long_job}").status_code == 204

    # The volume's page, not reloaded, reads the short job done once it is.
    page.wait_for_function(
        "id => document.querySelector(`#models a[href='/models/${id}']`)"
        "?.closest('li').textContent.includes('△')",
        arg=short_job,
    )
    text = entry(page, short_job).inner_text()
    assert "△" in text and "queued" not in text, text
    parts = len(server.model(short_job)["stats"].get("parts") or [])
    assert "1 parts" not in text and (parts != 1 or "1 part" in text), text
    assert re.search(r"\b20\d\d\b", text), text  # the date it was made
    page.screenshot(path=artifacts / "manage-volume-list.png")
    page.context.close()


def test_rename_and_delete_a_model_on_its_page(
    browser: Any, server: Server, head: str, artifacts: Path, logged_in: Any
) -> None:
    model_id = server.submit(head, level=280, sample_rate=4, decimate="none")
    assert server.wait_model(model_id)["status"] == "done"
    page = new_page(browser, server, logged_in)
    page.goto(f"/models/{model_id}")
    page.wait_for_function("() => window.__miss && window.__miss.ready")
    assert "level 280" in page.inner_text("#model-name")
    page.click("#rename")
    page.fill("#name-input", "Skull for the surgeon")
    page.click("#rename-form button[type=submit]")
    page.wait_for_function(
        "() => document.getElementById('model-name').textContent === 'Skull for the surgeon'"
    )
    page.reload()
    page.wait_for_function(
        "() => document.getElementById('model-name').textContent === 'Skull for the surgeon'"
    )
    page.screenshot(path=artifacts / "manage-renamed.png")

    page.goto(f"/volumes/{head}")
    entry(page, model_id).wait_for()
    assert entry(page, model_id).locator("a").inner_text() == "Skull for the surgeon"

    page.goto(f"/models/{model_id}")
    page.wait_for_function("() => window.__miss && window.__miss.ready")
    asked: list[str] = []

    def answer(dialog: Any, accept: bool) -> None:
        asked.append(dialog.message)
        dialog.accept() if accept else dialog.dismiss()

    page.once("dialog", lambda d: answer(d, False))
    page.click("#delete-model")
    assert "Skull for the surgeon" in asked[0] and "cannot be undone" in asked[0]
    assert server.http.get(f"/api/models/{model_id}").status_code == 200  # kept
    page.once("dialog", lambda d: answer(d, True))
    page.click("#delete-model")
    page.wait_for_url(f"**/volumes/{head}")
    assert server.http.get(f"/api/models/{model_id}").status_code == 404
    page.context.close()


@pytest.fixture(scope="module")
def colleague(server: Server) -> dict[str, str]:
    """Another account, with the PACS permission (the server has no PACS configured)."""
    body = {"name": "colleague", "password": "colleague-password", "pacs": True}
    assert server.http.post("/api/users", json=body).status_code == 201
    return body


def test_a_colleague_reads_the_model_is_not_shared_with_them(
    browser: Any,
    server: Server,
    head: str,
    colleague: dict[str, str],
    artifacts: Path,
    logged_in: Any,
) -> None:
    model_id = server.submit(head, level=260, sample_rate=4, decimate="none")
    assert server.wait_model(model_id)["status"] == "done"
    page = new_page(browser, server, logged_in, "colleague", "colleague-password")
    page.goto(f"/models/{model_id}")
    page.wait_for_function("() => window.__miss && window.__miss.error")
    text = page.inner_text("#overlay")
    assert "not shared with you" in text and "ask its owner for a share link" in text, text
    page.screenshot(path=artifacts / "manage-not-shared.png")
    page.context.close()


def test_no_send_to_pacs_without_a_pacs(
    browser: Any,
    server: Server,
    phantom: Path,
    colleague: dict[str, str],
    artifacts: Path,
    logged_in: Any,
) -> None:
    """The colleague's own model: everything but "Send to PACS", which has nowhere to go."""
    body = {"username": "colleague", "password": colleague["password"]}
    r = server.http.post("/api/auth/login", json=body)
    server.http.cookies.clear()  # the client stays the administrator's
    theirs = {"Authorization": f"Bearer {r.json()['token']}"}
    volume = upload(server, phantom.read_bytes(), "phantom-head.nii.gz", theirs)
    job = {"volume": volume, "level": 300, "sample_rate": 4, "decimate": "none"}
    own = server.http.post("/api/models", json=job, headers=theirs).json()["id"]
    assert server.wait_model(own)["status"] == "done"
    page = new_page(browser, server, logged_in, "colleague", colleague["password"])
    page.goto(f"/models/{own}")
    page.wait_for_function("() => window.__miss && window.__miss.ready")
    page.locator("#share").wait_for()
    page.wait_for_load_state("networkidle")  # the page has asked what it offers
    assert not page.is_visible("#send-pacs")
    page.screenshot(path=artifacts / "manage-no-pacs.png")
    page.context.close()


def test_the_library_lists_newest_first_and_searches(
    browser: Any, server: Server, artifacts: Path, logged_in: Any
) -> None:
    """Issue 42: after a reload the library shows the newest upload first (it came last
    before), a search box narrows the cards as one types with a count ("1 of N"), and a
    NIfTI scan's kind reads "MR · NIfTI" (what its values say, its format), not "volume"."""
    data = np.zeros((16, 16, 8), dtype=np.int16)  # values no CT has: an MR-like scan
    data[4:12, 4:12, 2:6] = 400
    first = upload(server, nib.Nifti1Image(data, np.eye(4)).to_bytes(), "first.nii")
    last = upload(server, nib.Nifti1Image(data + 1, np.eye(4)).to_bytes(), "second.nii")
    page = new_page(browser, server, logged_in)
    page.goto("/")
    page.wait_for_selector("body[data-ready='1']")
    ids = page.eval_on_selector_all("#volumes article", "cards => cards.map(c => c.dataset.id)")
    assert ids.index(last) < ids.index(first), ids
    total = len(ids)
    assert page.inner_text("#volume-count") == f"{total} volumes"
    card = page.locator(f"#volumes article[data-id='{first}']")
    assert card.locator(".facts").first.inner_text().startswith("MR · NIfTI · 16 × 16 × 8")
    page.fill("#volume-search", "DEMO phantom")  # every word, in any case
    shown = page.locator("#volumes article:visible")
    assert shown.count() == 1 and "Demo head phantom" in shown.inner_text()
    assert page.inner_text("#volume-count") == f"1 of {total} volumes"
    page.screenshot(path=artifacts / "library-search.png")
    page.fill("#volume-search", "no such scan anywhere")
    assert page.locator("#volumes article:visible").count() == 0
    assert page.locator("#no-match").is_visible()
    page.context.close()
