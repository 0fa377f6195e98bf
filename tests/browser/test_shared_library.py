"""The library as a colleague meets it: a share link they opened while signed in waits
under "Shared with me"; their volumes come newest first, also after a reload; the search
box narrows the cards as they type and says how many it shows; a NIfTI scan without a
modality reads "NIfTI", not "volume"."""

from __future__ import annotations

import gzip
from pathlib import Path
from typing import Any

import nibabel as nib
import numpy as np
import pytest
from browser.conftest import LAPTOP
from support.realserver import Server

READER = {"name": "reader42", "password": "reader42-password"}
PHONE = {"width": 390, "height": 844}


def ball(size: int = 32) -> bytes:
    """A ball of value 200 in 0: a NIfTI with no modality and nothing like CT's air."""
    grid = np.indices((size,) * 3) - size / 2
    data = ((grid**2).sum(axis=0) < (size / 3) ** 2).astype(np.int16) * 200
    return gzip.compress(nib.Nifti1Image(data, np.eye(4)).to_bytes(), compresslevel=1)


def upload(server: Server, name: str, headers: dict[str, str] | None = None) -> str:
    files = {"file": ("ball.nii.gz", ball())}
    r = server.http.post("/api/volumes", files=files, data={"name": name}, headers=headers or {})
    assert r.status_code == 201, r.text
    return r.json()["id"]


@pytest.fixture(scope="module")
def reader(server: Server) -> dict[str, str]:
    """A colleague's account and its three volumes, uploaded one after the other."""
    assert server.http.post("/api/users", json=READER).status_code == 201
    login = {"username": READER["name"], "password": READER["password"]}
    r = server.http.post("/api/auth/login", json=login)
    server.http.cookies.clear()  # the client stays the administrator's
    theirs = {"Authorization": f"Bearer {r.json()['token']}"}
    for name in ("Knee left", "Pelvis", "Shoulder right"):
        upload(server, name, theirs)
    return theirs


def reader_page(browser: Any, server: Server, logged_in: Any, viewport: dict) -> Any:
    context = browser.new_context(viewport=viewport, base_url=server.url)
    logged_in(context, READER["name"], READER["password"])
    page = context.new_page()
    page.set_default_timeout(60_000)
    return page


def library(page: Any) -> list[str]:
    """The names on the volume cards shown, top to bottom."""
    page.goto("/")
    page.wait_for_function("() => document.body.dataset.ready === '1'")
    return page.locator("#volumes .volume-card:visible .name").all_inner_texts()


def test_a_link_opened_signed_in_is_shared_with_me(
    browser: Any, server: Server, reader: dict, artifacts: Path, logged_in: Any
) -> None:
    volume = upload(server, "Temporal bone")  # the administrator's
    model = server.submit(volume, level=100, sample_rate=1, decimate="none")
    assert server.wait_model(model)["status"] == "done"
    made = server.post("/api/shares", {"model": model, "can_annotate": True})
    page = reader_page(browser, server, logged_in, LAPTOP)
    library(page)
    assert page.inner_text("#shared-section").splitlines()[-1].startswith("Links colleagues")
    page.goto(made["url"])
    page.wait_for_function("() => window.__miss && (window.__miss.ready || window.__miss.error)")
    library(page)
    item = page.locator("#shared-list li", has_text="Temporal bone")
    assert item.locator("a.name").get_attribute("href") == made["url"]
    assert "shared by admin" in item.inner_text() and "view, annotate" in item.inner_text()
    assert page.is_hidden("#shared-empty")
    page.screenshot(path=artifacts / "library-shared-laptop.png", full_page=True)
    item.locator("a.name").click()
    page.wait_for_url(f"**{made['url']}")
    page.context.close()


def test_newest_first_after_a_reload_search_and_format(
    browser: Any, server: Server, reader: dict, artifacts: Path, logged_in: Any
) -> None:
    page = reader_page(browser, server, logged_in, LAPTOP)
    assert library(page) == ["Shoulder right", "Pelvis", "Knee left"]
    page.reload()
    page.wait_for_function("() => document.body.dataset.ready === '1'")
    assert library(page) == ["Shoulder right", "Pelvis", "Knee left"]
    facts = page.locator("#volumes .volume-card .facts").first.inner_text()
    assert facts.startswith("MR · NIfTI · 32 × 32 × 32 voxels"), facts
    assert page.inner_text("#volume-count") == "3 volumes"
    page.fill("#volume-search", "pelv")
    assert page.locator("#volumes .volume-card:visible .name").all_inner_texts() == ["Pelvis"]
    assert page.inner_text("#volume-count") == "1 of 3 volumes"
    page.fill("#volume-search", "nifti right")
    assert page.inner_text("#volume-count") == "1 of 3 volumes"
    page.fill("#volume-search", "lung")
    assert page.inner_text("#volume-count") == "0 of 3 volumes"
    assert page.inner_text("#no-match") == "No volume matches “lung”."
    page.fill("#volume-search", "")
    assert page.inner_text("#volume-count") == "3 volumes"
    page.context.close()
    phone = reader_page(browser, server, logged_in, PHONE)
    library(phone)
    # Another browser never had the link (the server keeps no token): it says where to look.
    item = phone.locator("#shared-list li", has_text="Temporal bone")
    assert item.locator("a").count() == 0
    assert "this browser did not keep the link" in item.inner_text()
    phone.screenshot(path=artifacts / "library-shared-phone.png", full_page=True)
    box = phone.locator("#volume-search").bounding_box()
    assert box is not None and box["x"] >= 0 and box["x"] + box["width"] <= PHONE["width"]
    phone.context.close()
