"""The job form checks what is typed at the field, with the volume's own limits and in
the form's numbering (slices 1..N): nothing is swapped, clamped or left to Generate."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from support.realserver import Server


@pytest.fixture(scope="module")
def head(server: Server, phantom: Path) -> dict[str, Any]:
    r = server.http.post(
        "/api/volumes", files={"file": ("phantom-head.nii.gz", phantom.read_bytes())}
    )
    assert r.status_code == 201, r.text
    return r.json()


def said_at(page: Any, field: str) -> str:
    """What the page says beside the field, as a person reads it ('' when nothing)."""
    note = page.locator(f"#{field} ~ .field-error")
    return note.inner_text() if note.count() and note.is_visible() else ""


def test_values_are_checked_where_they_are_typed(
    page: Any, server: Server, head: dict[str, Any], artifacts: Path
) -> None:
    n = head["dims"][2]
    lo, hi = head["range"]
    page.goto(f"/volumes/{head['id']}")
    page.wait_for_selector("body[data-ready='1']")

    page.fill("#threshold", "99999")
    assert f"outside this volume's values {lo:g}..{hi:g}" in said_at(page, "threshold")
    page.fill("#threshold", "300")
    assert said_at(page, "threshold") == ""

    page.fill("#start-slice", "100")
    page.fill("#end-slice", "10")
    assert "Start slice 100 is after end slice 10" in said_at(page, "start-slice")
    assert (page.input_value("#start-slice"), page.input_value("#end-slice")) == ("100", "10")
    page.screenshot(path=artifacts / "form-checks-slices.png")

    page.fill("#end-slice", str(n))
    page.fill("#start-slice", "500")
    assert said_at(page, "start-slice") == f"Start slice must be a whole number from 1 to {n}."
    assert page.input_value("#start-slice") == "500"  # not clamped
    page.fill("#start-slice", "0")
    assert f"from 1 to {n}" in said_at(page, "start-slice")
    assert page.input_value("#start-slice") == "0"  # not made 1

    page.fill("#start-slice", "60")
    page.fill("#end-slice", "60")
    message = said_at(page, "end-slice")
    assert "slice 60 alone" in message and "59" not in message, message

    page.fill("#sample-rate", "abc")
    message = said_at(page, "sample-rate")
    assert "Sample rate “abc” is not one whole number" in message, message
    # Generate says the same at the first bad field and sends nothing.
    posted: list[str] = []
    page.on("request", lambda r: posted.append(r.url) if r.method == "POST" else None)
    page.click("#generate")
    bubble = page.evaluate("() => document.querySelector('input:invalid').validationMessage")
    assert "Please match" not in bubble and posted == [], (bubble, posted)
    page.screenshot(path=artifacts / "form-checks-sample-rate.png")

    page.fill("#sample-rate", "1")
    page.fill("#end-slice", "70")
    assert [said_at(page, f) for f in ("start-slice", "end-slice", "sample-rate")] == [""] * 3
    lines = page.inner_text(".view[data-axis=sagittal] .frame")
    assert "start 60" in lines and "end 70" in lines, lines
