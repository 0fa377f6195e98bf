"""A live consultation in two browsers: the owner, logged in, shares the model with a link
that allows annotating; a guest opens it without an account. The guest's camera follows
the presenter, a pin placed by one appears for the other, chat arrives, a reload keeps
the pins, and a revoked link is refused at once.

Screenshots go to test-artifacts/browser/consult-*.png.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import pytest

LAPTOP = {"width": 1366, "height": 768}
SAME_VIEW = """(t) => { const p = window.__miss.cameraLps().position;
    return Math.hypot(p[0] - t[0], p[1] - t[1], p[2] - t[2]) < 0.5; }"""
CONNECTED = "() => window.__miss && window.__miss.room && window.__miss.room.connected && !!window.__miss.room.you"


@pytest.fixture(scope="module")
def model_id(server: Any) -> str:
    """A small finished model of the demo head (the administrator's)."""
    demo = server.get("/api/volumes")[-1]["id"]  # the demo: the oldest, listed last
    job = server.post(
        "/api/models", {"volume": demo, "level": 300, "sample_rate": 4, "decimate": "none"}
    )
    assert server.wait_model(job["id"])["status"] == "done"
    return job["id"]


def watch_errors(page: Any) -> list[str]:
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(f"page error: {exc}"))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    return errors


@pytest.fixture
def owner(browser: Any, server: Any) -> Iterator[Any]:
    """The administrator's browser (it logs in through the login page in the test)."""
    context = browser.new_context(viewport=LAPTOP, base_url=server.url)
    page = context.new_page()
    page.errors = watch_errors(page)
    page.set_default_timeout(30_000)
    yield page
    context.close()


@pytest.fixture
def guest_context(browser: Any, server: Any) -> Iterator[Any]:
    """A browser with no account at all: only the link."""
    context = browser.new_context(viewport=LAPTOP, base_url=server.url)
    yield context
    context.close()


def room(page: Any) -> dict[str, Any]:
    return page.evaluate("() => window.__miss.room")


def camera(page: Any) -> list[float]:
    return page.evaluate("() => window.__miss.cameraLps().position")


def open_viewer(page: Any, url: str) -> None:
    page.goto(url)
    page.wait_for_function("() => window.__miss && window.__miss.ready", timeout=90_000)
    page.wait_for_function(CONNECTED)


def log_in_through_the_page(page: Any, path: str, password: str, artifacts: Any) -> None:
    """Opening a page without a session leads to the login, and back after it."""
    page.goto(path)
    page.wait_for_url("**/login?next=*")
    page.fill("#username", "admin")
    page.fill("#password", "not the password")
    page.click("#submit")
    page.wait_for_selector("#login-error:not([hidden])")
    assert "wrong user name or password" in page.inner_text("#login-error")
    page.screenshot(path=artifacts / "consult-login.png")
    page.fill("#password", password)
    page.click("#submit")
    page.wait_for_url(f"**{path}")
    page.errors.clear()  # the failed login's 401 is logged by the browser, as it should be


def share_through_dialog(page: Any, artifacts: Any) -> str:
    """The owner makes a consult link in the share dialog and copies its URL."""
    page.click("#share")
    page.wait_for_selector("#share-dialog[open]")
    page.fill("#share-label", "Dr Lee, island clinic")
    assert page.is_checked("#share-annotate") and not page.is_checked("#share-download")
    page.click("#share-create")
    page.wait_for_function("() => document.getElementById('share-url').value.includes('/s/')")
    url = page.input_value("#share-url")
    page.wait_for_selector("#share-list li[data-status=active]")
    page.screenshot(path=artifacts / "consult-share-dialog.png")
    page.click("#share-dialog button:has-text('Close')")
    return url


def drag(page: Any, dx: float) -> None:
    box = page.locator("#stage canvas").bounding_box()
    x, y = box["x"] + box["width"] * 0.5, box["y"] + box["height"] * 0.6
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + dx, y - dx / 4, steps=12)
    page.mouse.up()


def click_model(page: Any, dx: float = 0.0) -> None:
    box = page.locator("#stage canvas").bounding_box()
    page.mouse.click(box["x"] + box["width"] / 2 + dx, box["y"] + box["height"] / 2)


def test_two_browsers_consult_on_one_model(
    owner: Any,
    guest_context: Any,
    server: Any,
    model_id: str,
    artifacts: Any,
    admin_password: str,
) -> None:
    log_in_through_the_page(owner, f"/models/{model_id}", admin_password, artifacts)
    open_viewer(owner, f"/models/{model_id}")
    link = share_through_dialog(owner, artifacts)
    guest = guest_context.new_page()
    guest_errors = watch_errors(guest)
    guest.set_default_timeout(30_000)
    open_viewer(guest, link)
    assert "Shared by admin" in guest.inner_text("#share-title")
    assert "MISS" in guest.inner_text("#provenance") and "sha256:" in guest.inner_text(
        "#provenance"
    )
    guest.fill("#guest-name", "Dr Lee")
    guest.press("#guest-name", "Enter")
    owner.wait_for_function(
        "() => window.__miss.room.participants.some(p => p.name === 'Dr Lee (guest)')"
    )
    guest.wait_for_function(CONNECTED)
    following(owner, guest, artifacts)
    pins_and_chat(owner, guest, artifacts)
    # A reload brings the pins back (from the database, through the welcome).
    guest.reload()
    open_viewer(guest, guest.url)
    guest.wait_for_function("() => window.__miss.room.pins.length === 1")
    # ... and a late joiner is shown what the presenter shows now.
    guest.wait_for_function(SAME_VIEW, arg=camera(owner), timeout=15_000)
    assert "Look here" in guest.inner_text("#pins")
    assert "Can you see it?" in guest.inner_text("#chat-log")
    guest.screenshot(path=artifacts / "consult-guest-after-reload.png")
    assert not guest_errors and not owner.errors, guest_errors + owner.errors
    revoked(owner, guest, server, model_id, artifacts)
    replayed(owner, model_id, artifacts)


def following(owner: Any, guest: Any, artifacts: Any) -> None:
    """Presenter mode: the guest's camera eases to the presenter's, over several frames."""
    guest_before = camera(guest)
    owner.click("#present")
    owner.wait_for_function("() => window.__miss.room.presenter === window.__miss.room.you.id")
    guest.wait_for_function("() => window.__miss.room.following === true")
    # Record the guest's camera every frame while the presenter turns the model.
    guest.evaluate(
        """() => { window.__track = []; const tick = () => {
            window.__track.push(window.__miss.cameraLps().position);
            if (window.__track.length < 240) requestAnimationFrame(tick); };
          requestAnimationFrame(tick); }"""
    )
    drag(owner, 220)
    target = camera(owner)
    guest.wait_for_function(SAME_VIEW, arg=target, timeout=15_000)
    assert math.dist(camera(guest), target) < 0.5
    assert math.dist(guest_before, target) > 50  # it really moved
    track = guest.evaluate("() => window.__track")
    distinct = {tuple(round(v, 1) for v in p) for p in track}
    assert len(distinct) > 5, "the camera jumped instead of following smoothly"
    assert "Following admin" in guest.inner_text("#follow-state")
    owner.screenshot(path=artifacts / "consult-owner-presenting.png")
    guest.screenshot(path=artifacts / "consult-guest-following.png")


def pins_and_chat(owner: Any, guest: Any, artifacts: Any) -> None:
    guest.click("#room [data-tool=pin]")
    click_model(guest)
    guest.wait_for_selector("#pin-form:not([hidden])")
    guest.fill("#pin-note", "Look here")
    guest.press("#pin-note", "Enter")
    owner.wait_for_function("() => window.__miss.room.pins.some(p => p.note === 'Look here')")
    pin = next(p for p in room(owner)["pins"] if p["note"] == "Look here")
    assert pin["author"] == "Dr Lee (guest)" and len(pin["point"]) == 3
    assert "Look here" in owner.inner_text("#pins")
    owner.fill("#chat-input", "Can you see it?")
    owner.press("#chat-input", "Enter")
    guest.wait_for_function("() => window.__miss.room.chat.some(m => m.text === 'Can you see it?')")
    assert "Can you see it?" in guest.inner_text("#chat-log")
    owner.click("#room [data-tool=measure]")
    click_model(owner, -40)
    click_model(owner, 40)
    guest.wait_for_function("() => window.__miss.room.measurements.length === 1")
    mm = room(guest)["measurements"][0]["mm"]
    assert 5 < mm < 200, mm  # 80 px across a head, in millimetres
    owner.screenshot(path=artifacts / "consult-owner-pin-chat.png")
    guest.screenshot(path=artifacts / "consult-guest-pin-chat.png")


def revoked(owner: Any, guest: Any, server: Any, model_id: str, artifacts: Any) -> None:
    """Revoking closes the guest's room at once, and the link then opens a clear page."""
    shares = server.get("/api/shares")  # other tests' links to other models may be live
    (link,) = [s for s in shares if s["status"] == "active" and s["model"] == model_id]
    server.delete(f"/api/shares/{link['id']}")
    guest.wait_for_function(
        "() => window.__miss.room.closed && window.__miss.room.closed.code === 4410"
    )
    assert "expired or was revoked" in guest.inner_text("#room-error")
    response = guest.reload()
    assert response.status == 410
    assert "no longer valid" in guest.inner_text("h1")
    guest.screenshot(path=artifacts / "consult-link-revoked.png")


def replayed(owner: Any, model_id: str, artifacts: Any) -> None:
    """The owner replays the consultation: its events in order, the pin comes back.

    The consultation is the session with the most events, not always the first: the
    owner's first page (before ``open_viewer``) may have joined and left a room of its
    own, as it does when its socket connects before the page moves on (under load)."""
    owner.reload()
    open_viewer(owner, owner.url)
    sessions = owner.evaluate(
        "async (id) => (await fetch(`/api/models/${id}/room/sessions`)).json()", model_id
    )
    consultation = max(sessions, key=lambda s: s["events"])["session"]
    owner.click("#history-details summary")  # folded away below the model's sections
    owner.click(f"#sessions li[data-session='{consultation}'] button")
    owner.wait_for_function("() => window.__miss.replay.events > 0")
    owner.wait_for_function("() => !window.__miss.replay.playing", timeout=60_000)
    state = owner.evaluate("() => window.__miss.replay")
    assert state["shown"] == state["events"] and state["pins"] == 1
    log = owner.inner_text("#replay-log")
    for words in (
        "Guest (guest) is now Dr Lee (guest)",  # a rename, not a leave and a join
        "admin presents",
        "pinned “Look here”",
        "Can you see it?",
    ):
        assert words in log, (words, log)
    assert log.index("joined") < log.index("pinned") < log.index("Can you see it?")
    assert "Guest (guest) left" not in log
    owner.screenshot(path=artifacts / "consult-replay.png")
    owner.click("#replay-stop")


SET_RANGE = """([selector, value]) => {
    const input = document.querySelector(selector);
    input.value = String(value);
    input.dispatchEvent(new Event('input', { bubbles: true }));
}"""


def pin_at_centre(page: Any) -> list[float]:
    """Place a pin at the canvas's centre with the Pin tool; its point (LPS mm)."""
    before = len(room(page)["pins"])
    page.click("#room [data-tool=pin]")
    click_model(page)
    page.wait_for_selector("#pin-form:not([hidden])")
    page.fill("#pin-note", "here")
    page.press("#pin-note", "Enter")
    page.wait_for_function(f"() => window.__miss.room.pins.length === {before + 1}")
    return room(page)["pins"][-1]["point"]


def test_what_shows_is_shared_kept_and_picked_through(
    page: Any, guest_context: Any, server: Any
) -> None:
    """Issue 42: the owner hides a part and clips; a guest who joins sees the same, and so
    does the owner after a reload. A pin clicked where the 35 %-opaque skin lies over the
    bone lands on the bone (as when the skin is hidden) and selects nothing."""
    demo = server.get("/api/volumes")[-1]["id"]  # the demo: the oldest, listed last
    job = server.post(
        "/api/models",
        {"volume": demo, "levels": [300, -500], "sample_rate": 4, "decimate": "none"},
    )
    assert server.wait_model(job["id"])["status"] == "done"
    open_viewer(page, f"/models/{job['id']}")
    parts = page.evaluate("() => window.__miss.structures.parts")
    skin = next(i for i, p in enumerate(parts) if p["opacity"] < 1)
    rows = page.locator("#structure-list li")

    # the pin's pixel with the skin hidden: a point on the bone
    rows.nth(skin).locator("[data-role=visible]").uncheck()
    on_bone = pin_at_centre(page)
    rows.nth(skin).locator("[data-role=visible]").check()
    through = pin_at_centre(page)
    assert math.dist(on_bone, through) < 0.5, (on_bone, through)
    assert page.evaluate("() => window.__miss.structures.selected") is None

    bone = 1 - skin
    rows.nth(bone).locator("[data-role=visible]").uncheck()
    page.select_option("#clip-axis", "axial")
    page.evaluate(SET_RANGE, ["#clip-position", 0.5])
    link = server.post("/api/shares", {"model": job["id"], "can_annotate": True})["url"]
    guest = guest_context.new_page()
    open_viewer(guest, link)
    hidden = f"() => window.__miss.structures.parts[{bone}].visible === false"
    clipped = '() => JSON.stringify(window.__miss.structures.clip) === \'{"axis":"axial","fraction":0.5}\''
    guest.wait_for_function(hidden)
    guest.wait_for_function(clipped)  # the owner's last change may come after the welcome
    assert (
        not guest.locator("#structure-list li")
        .nth(bone)
        .locator("[data-role=visible]")
        .is_checked()
    )
    # Structures and Download come first in the side panel, the past sessions folded
    top = {s: guest.locator(s).bounding_box()["y"] for s in ("#structures-section", "#room")}
    assert top["#structures-section"] < top["#room"]
    page.reload()
    open_viewer(page, page.url)
    page.wait_for_function(hidden)
    sections = ("#structures-section", "#download-section", "#room", "#history")
    tops = [page.locator(s).bounding_box()["y"] for s in sections]
    assert tops == sorted(tops), dict(zip(sections, tops, strict=True))
    assert not page.locator("#sessions").is_visible()  # folded until asked for
    # names as people read them: "admin", not "admin (admin)"; "you" a badge of its own
    assert page.inner_text("#session-user") == "admin"
    assert "(you)" not in page.inner_text("#participants")
    assert page.locator("#participants .badge.you").count() == 1
    # a colleague signed in here who opens the link joins under their own name
    page.goto(link)
    page.wait_for_function(CONNECTED)
    assert page.evaluate("() => window.__miss.room.you.name") == "admin (guest)"
    page.wait_for_function(clipped)


def test_revoking_a_link_asks_first_and_forgets_its_url(page: Any, model_id: str) -> None:
    """Issue 42: Revoke asks before acting; once revoked the link leaves the list and its
    URL the copy field."""
    open_viewer(page, f"/models/{model_id}")
    page.click("#share")
    page.wait_for_selector("#share-dialog[open]")
    page.fill("#share-label", "to revoke")
    page.click("#share-create")
    page.wait_for_function("() => document.getElementById('share-url').value.includes('/s/')")
    item = page.locator("#share-list li[data-status=active]", has_text="to revoke")
    asked: list[str] = []
    page.once("dialog", lambda d: (asked.append(d.message), d.dismiss()))
    item.locator("button.danger").click()
    page.wait_for_timeout(300)  # a refused confirmation changes nothing
    assert asked and "Revoke" in asked[0] and item.count() == 1
    page.once("dialog", lambda d: d.accept())
    item.locator("button.danger").click()
    item.wait_for(state="detached")
    assert page.input_value("#share-url") == "" and not page.is_visible("#share-result")
    assert "revoked link" in page.inner_text("#share-list")
