"""The volume page's form takes its defaults and ranges from the API's schema (GET
/openapi.json, made from miss.spec), not from its own markup: browser-free checks that the
schema carries them and the page hard-codes none (tests/browser/test_pages.py runs the page)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

import miss
from miss.server.core.schemas import ModelRequest
from miss.spec import default_of, form_fields, form_name

WEB = Path(miss.__file__).parent / "web"
#: The form's inputs (volume-page.js FORM_FIELDS) and the job fields they fill.
INPUTS = {
    "components": "components",
    "min_size_mm3": "min-size",
    "start_slice": "start-slice",
    "end_slice": "end-slice",
    "sample_rate": "sample-rate",
    "decimate": "decimate",
    "error_bound": "error-bound",
    "reduce": "reduce",
}


@pytest.fixture(scope="module")
def form(client: TestClient) -> dict:
    return client.get("/openapi.json").json()["components"]["schemas"]["ModelRequest"]


def test_the_schema_carries_the_pages_ranges(form: dict) -> None:
    ranges = {name: p.get("x-form") for name, p in form["properties"].items() if "x-form" in p}
    # the page's ranges as they were in its markup (behaviour unchanged)
    assert ranges == {
        "start_slice": {"min": 1},
        "end_slice": {"min": 1},
        "min_size_mm3": {"min": 0.0},
        "error_bound": {"min": 0.00001, "max": 0.01},
        "reduce": {"min": 0.0, "max": 0.99},
    }


def test_the_schema_carries_the_specs_defaults(form: dict) -> None:
    for _, _, f in form_fields():
        name = form_name(f)
        if name in INPUTS:
            assert form["properties"][name].get("default") == default_of(f), name


def test_the_ranges_are_offered_not_checked() -> None:
    """The REST body keeps the declaration's own checks: a bound or a reduce beyond the
    page's range is a job, as before."""
    spec = ModelRequest(volume="v", level=300, error_bound=0.02, reduce=0.995).spec()
    assert (spec.decimation.error_bound, spec.decimation.reduce) == (0.02, 0.995)


def test_the_page_hard_codes_no_default_or_range() -> None:
    page = (WEB / "volume.html").read_text(encoding="utf-8")
    script = (WEB / "js" / "pages" / "volume-page.js").read_text(encoding="utf-8")
    for name, element in INPUTS.items():
        tag = re.search(rf"<(input|select)[^>]*\bid=\"{element}\"[^>]*>", page)
        assert tag is not None, element
        assert not re.search(r"\b(value|min|max)=", tag.group(0)), tag.group(0)
        assert f"{name}: '{element}'" in script, name
    assert "selected>" not in page  # the selects' defaults too
    assert "x-form" in script
