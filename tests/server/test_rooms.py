"""Consultation rooms over WebSocket: presence, presenter and camera, laser, pins,
measurements and chat stored and restored, the replay record, and every kind of bad
input refused with a clear message while the room goes on.

All sockets go through the module's one running TestClient (one event loop, as under
uvicorn); who connects is said by headers or the ``share`` query alone.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from datetime import timedelta
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update
from starlette.websockets import WebSocketDisconnect

from miss.server.rooms import BURST, MAX_MESSAGE_BYTES, RATE
from miss.server.rooms import hub as room_hub
from miss.server.rooms import people as room_people
from miss.server.rooms import record as roomlog
from miss.server.storage.db import ShareRow, utcnow

NOBODY = {"Authorization": ""}  # overrides the client's own admin token


@pytest.fixture(scope="module")
def room(client: TestClient, people: dict, small_nifti: bytes, upload_for, model_for) -> dict:
    """alice's model (a ball of radius 8 voxels) and a link to it that allows annotating."""
    alice = people["alice"]
    volume = upload_for(client, alice, small_nifti)
    model = model_for(client, alice, volume["id"])
    lo, hi = model["stats"]["bounds_mm"]
    link = link_for(client, alice, model["id"])
    centre = [(a + b) / 2 for a, b in zip(lo, hi, strict=True)]
    return {"alice": alice, "model": model["id"], "token": link, "centre": centre}


def link_for(
    client: TestClient, headers: dict, model_id: str, annotate: bool = True, hours: int = 168
) -> str:
    body = {"model": model_id, "can_annotate": annotate, "expires_in": hours * 3600}
    r = client.post("/api/shares", json=body, headers=headers)
    assert r.status_code == 201, r.text
    return r.json()["url"][3:]


def url(model_id: str, token: str = "", name: str = "") -> str:
    query = f"?share={token}&name={name}" if token else ""
    return f"/ws/rooms/{model_id}{query}"


@contextlib.contextmanager
def joined(client: TestClient, path: str, headers: dict | None = None) -> Iterator[Any]:
    """A connection that has read its welcome (kept as ``ws.welcome``)."""
    with client.websocket_connect(path, headers=headers or NOBODY) as ws:
        ws.welcome = ws.receive_json()
        assert ws.welcome["type"] == "welcome", ws.welcome
        yield ws


def until(ws: Any, kind: str, limit: int = 50) -> dict:
    """The next message of ``kind``, skipping others (presence, broadcasts)."""
    for _ in range(limit):
        message = ws.receive_json()
        if message["type"] == kind:
            return message
    raise AssertionError(f"no {kind!r} message in {limit}")


def refusal(client: TestClient, path: str, headers: dict | None = None) -> tuple[str, int]:
    """(error text, close code) of a connection the room will not take."""
    with client.websocket_connect(path, headers=headers or NOBODY) as ws:
        first = ws.receive_json()
        assert first["type"] == "error" and first["code"] == "refused", first
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
    return first["error"], closed.value.code


def test_presence_pins_chat_measure_and_replay(client: TestClient, room: dict) -> None:
    model, centre = room["model"], room["centre"]
    with joined(client, url(model), room["alice"]) as alice:
        assert alice.welcome["you"]["name"] == "alice" and alice.welcome["you"]["owner"]
        with joined(client, url(model, room["token"], "Dr Lee")) as guest:
            you = guest.welcome["you"]
            assert you["name"] == "Dr Lee (guest)" and you["guest"] and not you["owner"]
            assert len(guest.welcome["participants"]) == 2
            assert until(alice, "joined")["participant"]["colour"] != alice.welcome["you"]["colour"]
            guest.send_json({"type": "pin", "model": model, "point": centre, "note": "lesion?"})
            pin = until(alice, "pin")["item"]
            assert pin == until(guest, "pin")["item"]
            assert pin["note"] == "lesion?" and pin["author"] == "Dr Lee (guest)" and pin["at"]
            alice.send_json({"type": "chat", "text": "I see it"})
            assert until(guest, "chat")["item"]["text"] == "I see it"
            b = [centre[0] + 3, centre[1] + 4, centre[2]]
            alice.send_json({"type": "measure", "a": centre, "b": b})
            assert until(guest, "measure")["item"]["mm"] == pytest.approx(5.0)
            presenting_and_pointing(alice, guest, centre)
    with joined(client, url(model), room["alice"]) as again:  # a later session
        assert [p["note"] for p in again.welcome["pins"]] == ["lesion?"]
        assert [c["text"] for c in again.welcome["chat"]] == ["I see it"]
        assert [m["mm"] for m in again.welcome["measurements"]] == [5.0]
        assert again.welcome["session"] >= 2
    events = replay(client, model, room["alice"], leaves=3)
    first = [e for e in events if e["session"] == 1]
    kinds = [e["kind"] for e in first]
    assert kinds[:2] == ["join", "join"] and kinds.count("leave") == 2
    # each person's last event is their leave (the test client runs each socket on its own
    # loop, so alice's last view may be written after the guest's leave)
    for who in {"alice", "Dr Lee (guest)"}:
        assert [e["kind"] for e in first if e["author"] == who][-1] == "leave", who
    assert {"pin", "chat", "measure", "presenter", "view"} <= set(kinds)
    assert [e["at"] for e in events] == sorted(e["at"] for e in events)
    sessions = client.get(f"/api/models/{model}/room/sessions", headers=room["alice"]).json()
    assert sessions[0]["session"] == 1 and "alice" in sessions[0]["people"]


def replay(client: TestClient, model: str, headers: dict, leaves: int) -> list[dict]:
    """The room's events once ``leaves`` leave events are in (written as sockets close)."""
    deadline = time.monotonic() + 5
    while True:
        events = client.get(f"/api/models/{model}/room/events", headers=headers).json()
        if sum(e["kind"] == "leave" for e in events) >= leaves or time.monotonic() > deadline:
            return events
        time.sleep(0.05)


def presenting_and_pointing(alice: Any, guest: Any, centre: list[float]) -> None:
    """Presenter mode: others receive the presenter's camera; a non-presenter's is refused;
    a laser point reaches the others with the pointer's colour."""
    alice.send_json({"type": "presenter", "on": True})
    assert until(guest, "presenter")["id"] == alice.welcome["you"]["id"]
    view = {"position": [0, -300, 0], "target": centre, "up": [0, 0, 1]}
    alice.send_json({"type": "camera", **view})
    camera = until(guest, "camera")
    assert camera["position"] == [0, -300, 0] and camera["from"] == alice.welcome["you"]["id"]
    guest.send_json({"type": "camera", **view})
    assert until(guest, "error")["code"] == "not_presenter"
    guest.send_json({"type": "laser", "point": centre})
    laser = until(alice, "laser")
    assert laser["point"] == centre and laser["colour"] == guest.welcome["you"]["colour"]


BAD = [
    ("not json at all", "malformed"),
    ("[1, 2, 3]", "malformed"),
    ('{"type": "dance"}', "unknown_type"),
    ('{"type": "chat", "text": ""}', "invalid"),
    ('{"type": "chat", "text": 12}', "invalid"),
    ('{"type": "pin", "point": ["a", 0, 0], "note": "x"}', "invalid"),
    ('{"type": "pin", "point": [1e308, 0, 0], "note": "x"}', "invalid"),
    ('{"type": "pin", "point": [5000, 0, 0], "note": "far away"}', "off_model"),
    ('{"type": "pin", "model": "another-model", "point": [0, 0, 0]}', "wrong_model"),
    ('{"type": "unpin", "id": 999999}', "invalid"),
    ('{"type": "presenter", "on": "yes"}', "invalid"),
]


def test_bad_messages_are_refused_and_the_room_goes_on(client: TestClient, room: dict) -> None:
    model = room["model"]
    with (
        joined(client, url(model), room["alice"]) as alice,
        joined(client, url(model, room["token"], "Guest")) as guest,
    ):
        until(alice, "joined")
        for raw, code in BAD:
            alice.send_text(raw)
            error = until(alice, "error")
            assert error["code"] == code and error["error"], (raw, error)
        alice.send_text('{"type": "chat", "text": "' + "x" * (MAX_MESSAGE_BYTES + 10) + '"}')
        error = until(alice, "error")
        assert error["code"] == "too_large" and str(MAX_MESSAGE_BYTES) in error["error"]
        alice.send_bytes(b"\x00\x01binary")
        assert until(alice, "error")["code"] == "malformed"
        alice.send_json({"type": "pin", "point": room["centre"], "note": "mine"})
        pin = until(guest, "pin")["item"]
        guest.send_json({"type": "unpin", "id": pin["id"]})  # not the guest's pin
        assert until(guest, "error")["code"] == "forbidden"
        alice.send_json({"type": "ping"})
        assert until(alice, "pong") == {"type": "pong"}
        alice.send_json({"type": "chat", "text": "still here"})
        assert until(guest, "chat")["item"]["text"] == "still here"
        alice.send_json({"type": "unpin", "id": pin["id"]})
        assert until(guest, "unpin")["id"] == pin["id"]


def test_a_flood_is_cut_off_and_the_others_go_on(client: TestClient, room: dict) -> None:
    model = room["model"]
    with (
        joined(client, url(model), room["alice"]) as alice,
        joined(client, url(model, room["token"], "Quiet")) as quiet,
    ):
        with joined(client, url(model, room["token"], "Noisy")) as noisy:
            start = time.monotonic()
            for _ in range(400):
                noisy.send_json({"type": "ping"})
            seen: list[dict] = []
            with pytest.raises(WebSocketDisconnect) as closed:
                while True:
                    seen.append(noisy.receive_json())
            elapsed = time.monotonic() - start
            assert closed.value.code == 1008
            codes = [m.get("code") for m in seen if m["type"] == "error"]
            assert "rate_limited" in codes and codes[-1] == "flood"
            # The burst, and what the bucket refilled meanwhile (a loaded machine is slow).
            pongs = sum(m["type"] == "pong" for m in seen)
            assert BURST <= pongs <= BURST + RATE * elapsed + 1, (pongs, elapsed)
            assert pongs < 400 / 2
        alice.send_json({"type": "chat", "text": "after the storm"})
        assert until(quiet, "chat")["item"]["text"] == "after the storm"


def expire(client: TestClient, token: str) -> None:
    from miss.server.accounts import token_hash

    with client.app.state.store.session.begin() as s:
        past = utcnow() - timedelta(seconds=1)
        s.execute(
            update(ShareRow).where(ShareRow.token_hash == token_hash(token)).values(expires_at=past)
        )


def test_who_may_not_enter(
    client: TestClient, room: dict, people: dict, admin_password: str
) -> None:
    model, alice = room["model"], room["alice"]
    assert refusal(client, url(model))[1] == 4401  # no credentials
    assert refusal(client, url(model, "x" * 43))[1] == 4401  # no such link
    view_only = link_for(client, alice, model, annotate=False)
    text, code = refusal(client, url(model, view_only))
    assert code == 4403 and "viewing only" in text
    assert refusal(client, url(model), people["bob"])[1] == 4404  # not bob's model
    assert refusal(client, url("no-such-model"), alice)[1] == 4404
    demo = client.get("/api/models").json()  # the admin's list has models of others
    other = next((m["id"] for m in demo if m["id"] != model), None)
    if other is not None:
        assert refusal(client, url(other, room["token"]))[1] == 4404  # link is for one model
    expired = link_for(client, alice, model)
    expire(client, expired)
    text, code = refusal(client, url(model, expired))
    assert code == 4410 and "expired" in text
    # A cookie session, but the socket opened by another site's page.
    client.post("/api/auth/login", json={"username": "admin", "password": admin_password})
    try:
        foreign = {**NOBODY, "Origin": "http://evil.example"}
        text, code = refusal(client, url(model), foreign)
        assert code == 4403 and "cross-site" in text
    finally:
        client.cookies.clear()


def test_revoking_or_expiring_a_link_closes_its_guests(
    client: TestClient, room: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    model, alice = room["model"], room["alice"]
    for how in ("revoke", "expire"):
        token = link_for(client, alice, model, hours=1)
        with (
            joined(client, url(model), alice) as owner,
            joined(client, url(model, token, "Soon gone")) as guest,
        ):
            until(owner, "joined")
            if how == "revoke":
                share_id = client.get("/api/shares", headers=alice).json()[0]["id"]
                assert client.delete(f"/api/shares/{share_id}", headers=alice).status_code == 204
            else:  # two hours later: the link has run out, the owner's login has not
                later = lambda: utcnow() + timedelta(hours=2)  # noqa: E731
                monkeypatch.setattr(room_people, "utcnow", later)  # access checks
                monkeypatch.setattr(room_hub, "utcnow", later)  # event times
                guest.send_json({"type": "ping"})
            assert until(guest, "error")["code"] == {"revoke": "revoked", "expire": "expired"}[how]
            with pytest.raises(WebSocketDisconnect) as closed:
                until(guest, "never")
            assert closed.value.code == 4410
            monkeypatch.undo()
            owner.send_json({"type": "ping"})
            assert until(owner, "pong")["type"] == "pong"


def test_an_expired_link_closes_its_guests_unasked(
    client: TestClient, room: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Expiry needs no message from the guest: the hub's watcher closes the connection
    within a second of the link running out, with a reason."""
    model, alice = room["model"], room["alice"]
    token = link_for(client, alice, model, hours=1)
    with joined(client, url(model, token, "Quiet guest")) as guest:
        later = lambda: utcnow() + timedelta(hours=2)  # noqa: E731
        monkeypatch.setattr(room_people, "utcnow", later)  # access checks
        monkeypatch.setattr(room_hub, "utcnow", later)  # event times
        start = time.monotonic()
        assert until(guest, "error")["code"] == "expired"
        with pytest.raises(WebSocketDisconnect) as closed:
            until(guest, "never")
        assert closed.value.code == 4410 and time.monotonic() - start < 1.0


def test_times_rise_with_ids_across_a_rooms_sessions(
    client: TestClient, room: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The last leave of a session may still be being written when the next session's
    first join comes (a slow disk: the leave takes 0.3 s here). The join waits for it,
    so the record's order (by id, as the replay plays it) is also its order in time."""
    model, alice = room["model"], room["alice"]
    append = roomlog.append

    def slow_leave(store: Any, model_id: str, session: int, kind: str, *rest: Any) -> Any:
        if kind == "leave":
            time.sleep(0.3)
        return append(store, model_id, session, kind, *rest)

    monkeypatch.setattr(roomlog, "append", slow_leave)
    # the earlier tests' last leaves may still be on their way: wait for one per join
    joins = sum(e["kind"] == "join" for e in replay(client, model, alice, leaves=0))
    before = replay(client, model, alice, leaves=joins)
    leaves = sum(e["kind"] == "leave" for e in before)
    for _ in range(3):
        with joined(client, url(model), alice):
            pass
    events = replay(client, model, alice, leaves=leaves + 3)[len(before) :]
    assert [e["kind"] for e in events] == ["join", "leave"] * 3
    assert [e["at"] for e in events] == sorted(e["at"] for e in events), events


def test_what_shows_is_shared_and_kept(client: TestClient, room: dict) -> None:
    """Issue 42: the owner's (or presenter's) parts shown, opacity and clipping reach the
    others and are kept: a reload (a new connection) and a late guest get them back; a
    guest who does not present may not set them; bad states are refused."""
    model = room["model"]
    display = {
        "type": "display",
        "parts": [{"visible": False, "opacity": 0.35}, {"visible": True, "opacity": 1}],
        "clip": {"axis": "axial", "fraction": 0.6},
    }
    with (
        joined(client, url(model), room["alice"]) as alice,
        joined(client, url(model, room["token"], "Guest")) as guest,
    ):
        alice.send_json(display)
        heard = until(guest, "display")
        assert heard["item"]["parts"] == [
            {"visible": False, "opacity": 0.35},
            {"visible": True, "opacity": 1.0},
        ]
        assert heard["item"]["clip"] == {"axis": "axial", "fraction": 0.6}
        assert heard["from"] == alice.welcome["you"]["id"]
        guest.send_json(display | {"clip": None})
        assert until(guest, "error")["code"] == "not_presenter"
        for bad in (
            {"parts": "all"},
            {"parts": [{"visible": "yes", "opacity": 1}]},
            {"parts": [{"visible": True, "opacity": 2}]},
            {"parts": [], "clip": {"axis": "diagonal", "fraction": 0.5}},
            {"parts": [{"visible": True, "opacity": 1}] * 513},
        ):
            alice.send_json({"type": "display", **bad})
            assert until(alice, "error")["code"] == "invalid", bad
    with joined(client, url(model, room["token"], "Late")) as late:
        kept = late.welcome["display"]
        assert kept["parts"][0] == {"visible": False, "opacity": 0.35}
        assert kept["clip"] == {"axis": "axial", "fraction": 0.6}
        visit = late.welcome["session"]
    # a visit without a word (join, leave) is no consultation: not listed
    listed = client.get(f"/api/models/{model}/room/sessions", headers=room["alice"]).json()
    assert listed and visit not in [entry["session"] for entry in listed]
    # presenting, a guest sets it for everyone (the owner too)
    with (
        joined(client, url(model), room["alice"]) as alice,
        joined(client, url(model, room["token"], "Guest")) as guest,
    ):
        guest.send_json({"type": "presenter", "on": True})
        until(alice, "presenter")
        guest.send_json(display | {"clip": None})
        assert until(alice, "display")["item"]["clip"] is None
        alice.send_json(display)  # the owner, while someone else presents
        assert until(alice, "error")["code"] == "not_presenter"


def test_the_volume_view_is_part_of_what_shows(client: TestClient, room: dict) -> None:
    """Issue 43: rooms follow the scan's view like the parts: whether the volume shows, its
    preset and its window reach the others and are kept; bad views are refused."""
    model = room["model"]
    parts = [{"visible": True, "opacity": 1}]
    volume = {"on": True, "preset": "CT soft tissue", "level": 40, "window": 400}
    with (
        joined(client, url(model), room["alice"]) as alice,
        joined(client, url(model, room["token"], "Guest")) as guest,
    ):
        alice.send_json({"type": "display", "parts": parts, "clip": None, "volume": volume})
        heard = until(guest, "display")["item"]["volume"]
        assert heard == volume | {"level": 40.0, "window": 400.0, "points": None}
        custom = {"on": True, "preset": "Custom", "level": 40, "window": 400,
                  "points": [[-100, 1, 0, 0, 0], [300, 1, 1, 0.5, 0.75]]}  # fmt: skip
        alice.send_json({"type": "display", "parts": parts, "clip": None, "volume": custom})
        assert until(guest, "display")["item"]["volume"]["points"] == custom["points"]
        for bad in (
            {"on": "yes"},
            {"on": True, "level": 40},
            {"on": True, "level": 40, "window": 0},
            {"on": True, "level": float("inf"), "window": 10},
            {"on": True, "preset": "x" * 41},
            "volume",
            {"on": True, "points": [[0, 1, 1, 1, 0.5]]},
            {"on": True, "points": [[10, 1, 1, 1, 0], [0, 1, 1, 1, 1]]},
            {"on": True, "points": [[0, 1, 1, 1, 0], [10, 1, 2, 1, 1]]},
            {"on": True, "points": [[0, 1, 1, 1, 0]] * 33},
        ):
            alice.send_json({"type": "display", "parts": parts, "clip": None, "volume": bad})
            assert until(alice, "error")["code"] == "invalid", bad
    with joined(client, url(model, room["token"], "Late")) as late:
        assert late.welcome["display"]["volume"]["preset"] == "Custom"


def test_the_linked_slices_and_crosshair_are_part_of_what_shows(
    client: TestClient, room: dict
) -> None:
    """Issue 43: rooms follow the crosshair like the camera: whether the linked slices show
    and where the crosshair is (LPS mm) reach the others and are kept; bad ones refused."""
    model = room["model"]
    parts = [{"visible": True, "opacity": 1}]
    slices = {"on": True, "point": [12.5, -40, 77]}
    with (
        joined(client, url(model), room["alice"]) as alice,
        joined(client, url(model, room["token"], "Guest")) as guest,
    ):
        alice.send_json({"type": "display", "parts": parts, "clip": None, "slices": slices})
        assert until(guest, "display")["item"]["slices"] == {
            "on": True,
            "point": [12.5, -40.0, 77.0],
        }
        for bad in (
            {"on": 1, "point": None},
            {"point": [0, 0, 0]},
            {"on": True, "point": [0, 0]},
            {"on": True, "point": [0, 0, float("nan")]},
            {"on": True, "point": [0, 0, 1e7]},
            {"on": True, "point": ["1", 0, 0]},
            [True, [0, 0, 0]],
        ):
            alice.send_json({"type": "display", "parts": parts, "clip": None, "slices": bad})
            assert until(alice, "error")["code"] == "invalid", bad
    with joined(client, url(model, room["token"], "Late")) as late:
        assert late.welcome["display"]["slices"] == {"on": True, "point": [12.5, -40.0, 77.0]}


def test_a_guest_renames_without_leaving(client: TestClient, room: dict) -> None:
    """Issue 42: a guest's new name is one ``rename`` event that everyone hears, not a
    leave and a join; an account's name is not the guest's to change."""
    model = room["model"]
    with (
        joined(client, url(model), room["alice"]) as alice,
        joined(client, url(model, room["token"], "Guest")) as guest,
    ):
        guest.send_json({"type": "rename", "name": "Dr Lee"})
        renamed = until(alice, "renamed")["participant"]
        assert renamed["name"] == "Dr Lee (guest)" and renamed["id"] == guest.welcome["you"]["id"]
        alice.send_json({"type": "rename", "name": "Mallory"})
        assert until(alice, "error")["code"] == "forbidden"
        session = guest.welcome["session"]
    kinds = [
        (e["kind"], e["author"])
        for e in client.get(
            f"/api/models/{model}/room/events", params={"session": session}, headers=room["alice"]
        ).json()
    ]
    assert ("rename", "Dr Lee (guest)") in kinds
    assert ("leave", "Guest (guest)") not in kinds  # the guest never left under the old name
