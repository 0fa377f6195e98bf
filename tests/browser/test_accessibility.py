"""axe-core (Deque's accessibility engine, from npm in tests/validators) on every page MISS
serves, as a person meets it: the login page, the library, a volume's page, a model's page
for its owner and for a share link's guest, at a laptop's size and a phone's. No serious or
critical violation may be left (issue 42); the full report of each page goes to
test-artifacts/browser/axe-*.json.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import LAPTOP

AXE = (
    Path(__file__).resolve().parents[1] / "validators" / "node_modules" / "axe-core" / "axe.min.js"
)
PHONE = {"width": 390, "height": 844}
SERIOUS = ("serious", "critical")
#: Rules of lesser impact that MISS's pages keep too (each page names itself in an h1).
KEPT = ("page-has-heading-one",)

if not AXE.is_file():
    pytest.skip(
        f"axe-core is not installed at {AXE} (`make validators` installs it)",
        allow_module_level=True,
    )


def violations(page: Any, name: str, artifacts: Path) -> list[str]:
    """axe's serious and critical violations on the page as it is now, one line each."""
    page.add_script_tag(path=str(AXE))  # the context bypasses the pages' CSP for it alone
    report = page.evaluate("async () => await axe.run(document, { resultTypes: ['violations'] })")
    (artifacts / f"axe-{name}.json").write_text(json.dumps(report["violations"], indent=1))
    return [
        f"{name}: {v['id']} ({v['impact']}): {v['help']} -- "
        + "; ".join(n["target"][0] if n["target"] else "?" for n in v["nodes"][:4])
        for v in report["violations"]
        if v["impact"] in SERIOUS or v["id"] in KEPT
    ]


@pytest.fixture(scope="module")
def model_and_link(server: Any) -> tuple[str, str, str]:
    """(volume id, a finished two-part model of the demo head, a link to it that allows
    consulting and downloads)."""
    demo = server.get("/api/volumes")[-1]["id"]  # the demo: the oldest, listed last
    parts = [{"level": 300, "name": "bone"}, {"level": -500, "name": "skin"}]
    body = {"volume": demo, "parts": parts, "sample_rate": 4, "decimate": "none"}
    model = server.wait_model(server.post("/api/models", body)["id"])
    assert model["status"] == "done", model["error"]
    link = server.post(
        "/api/shares", {"model": model["id"], "can_annotate": True, "can_download": True}
    )
    return demo, model["id"], link["url"]


@pytest.fixture(params=["laptop", "phone"])
def size(request: Any) -> tuple[str, dict[str, int]]:
    return request.param, LAPTOP if request.param == "laptop" else PHONE


@pytest.fixture
def owner(browser: Any, server: Any, size: tuple[str, dict[str, int]]) -> Iterator[Any]:
    from conftest import log_in_context

    context = browser.new_context(viewport=size[1], base_url=server.url, bypass_csp=True)
    log_in_context(context)
    yield context.new_page()
    context.close()


@pytest.fixture
def stranger(browser: Any, server: Any, size: tuple[str, dict[str, int]]) -> Iterator[Any]:
    context = browser.new_context(viewport=size[1], base_url=server.url, bypass_csp=True)
    yield context.new_page()
    context.close()


def test_the_pages_of_an_account(
    owner: Any, model_and_link: tuple[str, str, str], size: Any, artifacts: Path
) -> None:
    volume, model, _ = model_and_link
    found = []
    owner.goto("/")
    owner.wait_for_selector(".volume-card")
    found += violations(owner, f"library-{size[0]}", artifacts)
    owner.goto(f"/volumes/{volume}")
    owner.wait_for_selector("body[data-ready='1']")
    found += violations(owner, f"volume-{size[0]}", artifacts)
    owner.goto(f"/models/{model}")
    owner.wait_for_function("() => window.__miss && window.__miss.ready")
    found += violations(owner, f"model-{size[0]}", artifacts)
    assert not found, "\n".join(found)


def test_the_pages_without_an_account(
    stranger: Any, model_and_link: tuple[str, str, str], size: Any, artifacts: Path
) -> None:
    _, _, link = model_and_link
    found = []
    stranger.goto("/login")
    stranger.wait_for_selector("#username")
    found += violations(stranger, f"login-{size[0]}", artifacts)
    connected = "() => window.__miss && window.__miss.room && window.__miss.room.connected"
    first = stranger.context.new_page()  # in the room first: the second gets the next colour
    first.goto(link)
    first.wait_for_function(connected)
    stranger.goto(link)
    stranger.wait_for_function("() => window.__miss && window.__miss.ready")
    stranger.wait_for_function(connected)
    for page in (first, stranger):  # each name in the chat, in its colour, must be legible
        page.fill("#chat-input", "Can you see the fracture?")
        page.press("#chat-input", "Enter")
    stranger.wait_for_function("() => window.__miss.room.chat.length >= 2")
    found += violations(stranger, f"share-{size[0]}", artifacts)
    assert not found, "\n".join(found)


def test_the_3d_view_from_the_keyboard(page: Any, model_and_link: tuple[str, str, str]) -> None:
    """Issue 42: the 3-D view is reached with Tab, names itself, and turns and zooms with
    the keyboard (it was neither focusable nor named)."""
    import math

    _, model, _ = model_and_link
    page.goto(f"/models/{model}")
    page.wait_for_function("() => window.__miss && window.__miss.ready")
    canvas = page.locator("#stage canvas")
    assert "arrow keys" in (canvas.get_attribute("aria-label") or "")
    for _ in range(60):  # Tab from the top until the view has the focus
        page.keyboard.press("Tab")
        if (
            page.evaluate("() => document.activeElement && document.activeElement.tagName")
            == "CANVAS"
        ):
            break
    else:
        raise AssertionError("Tab never reached the 3-D view")
    pose = "() => window.__miss.cameraLps()"
    start = page.evaluate(pose)
    page.keyboard.press("ArrowLeft")
    turned = page.evaluate(pose)
    target = start["target"]
    assert math.dist(start["position"], turned["position"]) > 1.0
    distance = math.dist(turned["position"], target)
    assert abs(distance - math.dist(start["position"], target)) < 1e-3 * distance  # a turn
    page.keyboard.press("+")
    assert math.dist(page.evaluate(pose)["position"], target) < 0.9 * distance
    page.keyboard.press("ArrowUp")
    assert page.evaluate(pose)["position"] != turned["position"]


def test_the_view_is_in_the_address(
    page: Any, browser: Any, server: Any, model_and_link: tuple[str, str, str]
) -> None:
    """Issue 43 (deep links): the camera follows into the address (?cam=, LPS mm) as the
    view turns, and that address -- or a share link with it -- opens on the same view."""
    import math
    from urllib.parse import parse_qs, urlsplit

    _, model, link = model_and_link
    page.goto(f"/models/{model}")
    page.wait_for_function("() => window.__miss && window.__miss.ready")
    page.locator("#stage canvas").focus()
    page.keyboard.press("ArrowLeft")
    page.keyboard.press("ArrowUp")
    page.wait_for_function("() => location.search.includes('cam=')")
    seen = page.evaluate("() => window.__miss.cameraLps()")
    cam = parse_qs(urlsplit(page.url).query)["cam"][0]
    guest = browser.new_context(base_url=server.url, viewport=LAPTOP)
    try:  # the owner's address in a new tab, and the share link with the view
        for view, address in (
            (page.context.new_page(), page.url),
            (guest.new_page(), f"{link}?cam={cam}"),
        ):
            view.goto(address)
            view.wait_for_function(
                "() => window.__miss && window.__miss.ready && window.__miss.cameraLps"
            )
            got = view.evaluate("() => window.__miss.cameraLps()")
            assert math.dist(got["position"], seen["position"]) < 0.05, (address, got, seen)
            assert math.dist(got["target"], seen["target"]) < 0.05
    finally:
        guest.close()
