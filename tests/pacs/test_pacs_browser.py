"""The PACS pages as a physician uses them, in Debian's chromium against a real
``miss serve`` and a real Orthanc: log in, search the PACS from the library's From PACS
tab, import the CT series, generate a model, send it to the PACS, and find it there.

Screenshots land in test-artifacts/browser/ so a person can look at what the test saw.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import pytest

# chromium, its flags, the window and where screenshots go, as every browser test has
# them (that module skips these tests where chromium or Playwright is missing)
from browser.conftest import ARTIFACTS, LAPTOP
from support.realserver import Server, serving

from pacs.conftest import Series
from pacs.orthanc import Orthanc

GE = "ct_head_dicom_ge_gantrytilt"
ENCAPSULATED_STL = "1.2.840.10008.5.1.4.1.1.104.3"
USER, PASSWORD = "radiologist", "radiologist-password"


@pytest.fixture(scope="module")
def miss(
    orthanc: Orthanc, pacs_series: dict[str, Series], tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Server]:
    """``miss serve`` pointed at the Orthanc, with an account that may use it."""
    folder = tmp_path_factory.mktemp("pacs-browser")
    with serving(folder / "data", folder / "miss-serve.log", env=orthanc.env()) as server:
        r = server.http.post("/api/users", json={"name": USER, "password": PASSWORD, "pacs": True})
        assert r.status_code == 201, r.text
        yield server


@pytest.fixture
def page(browser: Any, miss: Server) -> Iterator[Any]:
    """A laptop-sized page, not logged in, whose script errors fail the test."""
    context = browser.new_context(viewport=LAPTOP, base_url=miss.url)  # session chromium
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(f"page error: {exc}"))

    def on_console(msg: Any) -> None:
        # chromium logs each 4xx answer; the test asks for one 422 on purpose
        if msg.type == "error" and "status of 422" not in msg.text:
            errors.append(f"console: {msg.text}")

    page.on("console", on_console)
    page.set_default_timeout(30_000)
    yield page
    context.close()
    assert not errors, "the page logged errors:\n" + "\n".join(errors)


def stl_instances(orthanc: Orthanc, study: str) -> list[dict[str, Any]]:
    """The study's Encapsulated STL instances, found by QIDO-RS."""
    from dicomweb_client import DICOMwebClient

    pacs = DICOMwebClient(orthanc.dicomweb)
    pacs._session.auth = (orthanc.user, orthanc.password)
    return pacs.search_for_instances(
        study_instance_uid=study, search_filters={"SOPClassUID": ENCAPSULATED_STL}
    )


def test_search_import_generate_and_send_to_pacs(
    page: Any, miss: Server, orthanc: Orthanc, pacs_series: dict[str, Series]
) -> None:
    ge = pacs_series[GE]
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()

    page.goto("/login?next=/")
    page.fill("#username", USER)
    page.fill("#password", PASSWORD)
    page.click("#submit")
    page.wait_for_url(f"{miss.url}/")
    page.wait_for_selector("body[data-ready='1']")

    # the From PACS tab: search by patient ID; the study row names the made-up patient
    page.click("#tab-pacs")
    assert page.is_hidden("#volumes-panel")
    # a filter the server refuses: its detail is shown, as it says what to fix
    page.fill("#pacs-study-date", "last week")
    page.click("#pacs-search-button")
    page.wait_for_selector("#pacs-error:not([hidden])")
    assert "study_date must be YYYYMMDD" in page.inner_text("#pacs-error")
    page.screenshot(path=ARTIFACTS / "pacs-bad-filter.png")
    page.fill("#pacs-study-date", "")
    page.fill("#pacs-patient-id", ge.patient_id)
    page.click("#pacs-search-button")
    study = page.locator(f"tr.pacs-study[data-study='{ge.study}']")
    study.wait_for()
    assert page.locator("tr.pacs-study").count() == 1
    assert ge.patient_id in study.inner_text() and "DOE" in study.inner_text()
    assert page.is_hidden("#pacs-more")

    # its series, then the import with its progress, then Open
    study.get_by_role("button").click()
    series = page.locator(f"tr[data-series='{ge.series}']")
    series.wait_for()
    assert "CT" in series.inner_text() and str(ge.instances) in series.inner_text()
    page.screenshot(path=ARTIFACTS / "pacs-series.png")
    series.get_by_role("button", name="Import").click()
    series.locator("progress").wait_for()
    page.screenshot(path=ARTIFACTS / "pacs-importing.png")
    series.locator(".pacs-import[data-done]").wait_for(timeout=120_000)
    page.screenshot(path=ARTIFACTS / "pacs-imported.png")
    volume_link = series.get_by_role("link", name="Open")
    volume_id = volume_link.get_attribute("href").rsplit("/", 1)[-1]
    # the volume joins the library's list, which shows nothing of the patient
    page.click("#tab-volumes")
    card = page.locator(f".volume-card[data-id='{volume_id}']")
    card.wait_for()
    for value in ("DOE", "JANE", ge.patient_id, ge.accession):
        assert value not in card.inner_text(), value
    page.screenshot(path=ARTIFACTS / "pacs-library.png")

    # generate a model of the bone, coarsely (sample rate 2) to keep the test short
    page.click("#tab-pacs")
    volume_link.click()
    page.wait_for_url(f"**/volumes/{volume_id}")
    page.wait_for_selector("body[data-ready='1']")
    page.click("#presets [data-preset=bone]")
    page.fill("#sample-rate", "2")
    page.click("#generate")
    page.wait_for_url("**/models/*")
    model_id = page.url.rstrip("/").split("/")[-1].split("?")[0]
    assert miss.wait(model_id, ("done", "failed"), timeout=150)["status"] == "done"

    # Send to PACS: the message names the PACS, the series description and the count
    before = len(stl_instances(orthanc, ge.study))  # other tests may have sent one
    send = page.locator("#send-pacs")
    send.wait_for()
    send.click()
    page.wait_for_selector("#pacs-result[data-sent]", timeout=60_000)
    message = page.inner_text("#pacs-result")
    assert message.startswith("Sent to Orthanc: MISS surface: "), message
    assert message.endswith("(1 instance)"), message
    page.screenshot(path=ARTIFACTS / "pacs-sent.png")

    # QIDO finds the Encapsulated STL in the patient's original study
    assert len(stl_instances(orthanc, ge.study)) == before + 1
    assert time.monotonic() - started < 150
