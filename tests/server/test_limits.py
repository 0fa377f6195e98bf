"""Limits that keep one client from starving the others: the API's rate limit per account
(per address without one), jobs queued or running per account, the upload size, people
per room. Each test also checks that somebody else is not affected.

Refill rates are set so low (one request per 100 s) that no test depends on timing.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from typing import Any

import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from miss.server.core.ratelimit import KeyedBuckets, SharedBuckets, split
from miss.server.rooms import Close

NOBODY = {"Authorization": ""}  # overrides the client's own admin token
SLOW = 0.01  # requests per second: nothing refills during a test


def add_user(client: TestClient, name: str) -> dict[str, str]:
    """A new ordinary account on ``client``'s app: its request headers (bearer token)."""
    r = client.post("/api/users", json={"name": name, "password": f"{name}-password"})
    assert r.status_code == 201, r.text
    r = client.post(
        "/api/auth/login",
        json={"username": name, "password": f"{name}-password"},
        headers=NOBODY,
    )
    assert r.status_code == 200, r.text
    client.cookies.clear()  # the client stays the administrator's
    return {"Authorization": f"Bearer {r.json()['token']}"}


def until_refused(client: TestClient, path: str, headers: dict[str, str], most: int) -> int:
    """Requests sent until the first 429 (which is checked); fails after ``most``."""
    for n in range(1, most + 1):
        r = client.get(path, headers=headers)
        if r.status_code == 429:
            assert_429(r)
            return n
        assert r.status_code < 500, r.text
    raise AssertionError(f"no 429 after {most} requests to {path}")


def assert_429(r: Any, *words: str) -> None:
    assert r.status_code == 429, r.text
    assert int(r.headers["retry-after"]) >= 1
    detail = r.json()["detail"]
    assert all(w in detail for w in words), detail


def test_api_rate_limit_per_account_then_per_address(
    make_client: Callable[..., TestClient],
) -> None:
    client = make_client(api_rate=SLOW, api_burst=20)
    alice, bob = add_user(client, "alice"), add_user(client, "bob")

    # alice's burst (her token's first request still counts against the address).
    sent = until_refused(client, "/api/volumes", alice, most=40)
    assert 20 <= sent <= 22, sent
    r = client.get("/api/volumes", headers=alice)
    assert_429(r, "this account", "per second", "retry in")
    assert int(r.headers["retry-after"]) > 60  # one token per 100 s
    # Nobody else is slowed down by her.
    assert client.get("/api/volumes", headers=bob).status_code == 200
    assert client.get("/api/volumes").status_code == 200  # the administrator

    # Without an account (a share link's viewer, a made-up token): the address's bucket.
    until_refused(client, "/s/no-such-link/info", NOBODY, most=40)
    assert_429(client.get("/s/no-such-link/info", headers=NOBODY), "the address testclient")
    made_up = {"Authorization": "Bearer made-up-token"}
    assert_429(client.get("/api/volumes", headers=made_up), "the address")
    # ... which leaves the accounts, monitoring, pages and assets alone.
    assert client.get("/api/volumes", headers=bob).status_code == 200
    assert client.get("/api/health", headers=NOBODY).status_code == 200
    assert client.get("/login", headers=NOBODY).status_code == 200
    assert client.get("/static/js/api.js", headers=NOBODY).status_code == 200
    assert client.get("/api/volumes", headers=alice).status_code == 429


def test_tiles_of_a_large_model_cost_a_share_of_a_request(
    make_client: Callable[..., TestClient],
) -> None:
    """A viewer zooming into a large model fetches dozens of tiles at once (levels of
    detail): each costs an eighth of a request, so a burst of 20 covers 160 of them."""
    client = make_client(api_rate=SLOW, api_burst=20)
    carol = add_user(client, "carol")
    tile = "/api/models/no-such-model/lod/tiles/r.glb"
    sent = until_refused(client, tile, carol, most=400)
    assert 150 <= sent <= 170, sent
    assert_429(client.get("/api/volumes", headers=carol), "this account")


def test_what_one_process_spends_is_taken_from_the_others_buckets() -> None:
    """Two processes' buckets for one key, each let through 6 of a burst of 10 before
    hearing of the other: once told, both refuse, and stay in debt (2 tokens) until they
    have refilled past it; a token given back (a good password) is given back on both.
    The same through PostgreSQL: ``test_processes.py``."""
    a, b = KeyedBuckets(10, SLOW), KeyedBuckets(10, SLOW)
    for buckets in (a, b):
        buckets.record()
    shared_a, shared_b = SharedBuckets({"api": a}), SharedBuckets({"api": b})
    for _ in range(6):
        assert a.take("user:1") and b.take("user:1") and b.take("user:2", 0.125)
    for message in split({"api": a.drain()}, 7000):
        shared_b.heard(message)
    for message in split({"api": b.drain()}, 7000):
        shared_a.heard(message)
    assert a.drain() == b.drain() == {}  # what was heard is not told again
    for buckets in (a, b):
        assert not buckets.take("user:1")
        assert buckets.take_or_wait("user:1") == pytest.approx(3 / SLOW, rel=0.01)
        assert buckets.take("user:2")  # another key: 0.75 of 10 spent
    b.give_back("user:1", 5)
    shared_a.heard({"api": b.drain()})
    assert a.take("user:1") and b.take("user:1")


def test_spending_of_many_keys_is_split_into_messages_that_fit() -> None:
    spent = {"api": {f"addr:10.0.{n // 256}.{n % 256}": 1.0 for n in range(1000)}}
    spent["login-accounts"] = {"ann": -1.0}
    messages = split(spent, 7000)
    assert len(messages) > 1
    assert all(len(json.dumps(m, separators=(",", ":"))) <= 7000 for m in messages)
    joined: dict[str, dict[str, float]] = {}
    for message in messages:
        for name, keys in message.items():
            joined.setdefault(name, {}).update(keys)
    assert joined == spent
    assert split({"api": {}}, 7000) == []


@pytest.mark.slow
def test_jobs_per_account(
    make_client: Callable[..., TestClient],
    small_nifti: bytes,
    upload_for: Callable[..., dict[str, Any]],
    model_for: Callable[..., dict[str, Any]],
) -> None:
    client = make_client(max_jobs_per_user=1)
    alice, bob = add_user(client, "alice"), add_user(client, "bob")
    mine = upload_for(client, alice, small_nifti)["id"]
    theirs = upload_for(client, bob, small_nifti)["id"]
    done = model_for(client, alice, mine, level=0.0)
    # From here on jobs stay queued: the real queue, stopped, so that "queued or
    # running" does not depend on how fast a worker is.
    client.app.state.queue.stop()

    def submit(headers: dict[str, str], volume: str, level: float) -> Any:
        body = {"volume": volume, "level": level, "decimate": "none"}
        return client.post("/api/models", json=body, headers=headers)

    first = submit(alice, mine, 100.0)
    assert first.status_code == 202, first.text
    # Asking again for a model that is queued or done queues nothing: never refused.
    assert submit(alice, mine, 100.0).json()["id"] == first.json()["id"]
    again = submit(alice, mine, 0.0)
    assert again.status_code == 200 and again.json()["id"] == done["id"]
    # A new one would be her second at once.
    refused = submit(alice, mine, -100.0)
    assert_429(refused, "you already have 1 model being generated", first.json()["id"], "cancel")
    # Others are not held up: bob, and the administrator on alice's own volume.
    assert submit(bob, theirs, 100.0).status_code == 202
    assert submit({}, mine, 200.0).status_code == 202
    # Cancelling hers frees her slot.
    assert client.delete(f"/api/models/{first.json()['id']}", headers=alice).status_code == 204
    assert submit(alice, mine, -100.0).status_code == 202

    # A share link is no session: it cannot submit jobs at all.
    r = client.post("/api/shares", json={"model": done["id"], "can_annotate": True}, headers=alice)
    token = r.json()["url"].removeprefix("/s/")
    r = submit({"Authorization": f"Bearer {token}"}, mine, 300.0)
    assert r.status_code == 401, r.text


def test_upload_over_the_size_limit(make_client: Callable[..., TestClient]) -> None:
    client = make_client(max_upload_mb=0.25)  # 256 KiB
    r = client.post("/api/volumes", files={"file": ("big.nii.gz", os.urandom(400_000))})
    assert r.status_code == 413, r.text
    assert "larger than the limit of 0.25 MB" in r.json()["detail"], r.json()
    assert client.get("/api/volumes").json() == []
    tmp = client.app.state.settings.data_dir / "tmp"
    assert not tmp.exists() or list(tmp.iterdir()) == []  # nothing of it left behind


@pytest.mark.slow
def test_people_per_room_and_rooms_apart_from_the_api_limit(
    make_client: Callable[..., TestClient],
    small_nifti: bytes,
    upload_for: Callable[..., dict[str, Any]],
    model_for: Callable[..., dict[str, Any]],
) -> None:
    client = make_client(api_rate=SLOW)  # bursts of 200
    volume = upload_for(client, {}, small_nifti)["id"]
    model = model_for(client, {}, volume)["id"]
    r = client.post("/api/shares", json={"model": model, "can_annotate": True})
    token = r.json()["url"].removeprefix("/s/")
    client.app.state.rooms.max_people = 2  # rooms.MAX_PEOPLE is 50; the same code path
    client.app.state.rooms.reserved = 0  # no place kept for the owner: guests fill it
    # The address has used up its API requests; its WebSockets are limited elsewhere.
    until_refused(client, "/api/no-such-route", NOBODY, most=250)

    path = f"/ws/rooms/{model}?share={token}&name="
    with (
        client.websocket_connect(path + "One", headers=NOBODY) as one,
        client.websocket_connect(path + "Two", headers=NOBODY) as two,
    ):
        assert one.receive_json()["type"] == "welcome"
        assert two.receive_json()["type"] == "welcome"
        with client.websocket_connect(path + "Three", headers=NOBODY) as three:
            first = three.receive_json()
            assert first["type"] == "error" and "full" in first["error"], first
            with pytest.raises(WebSocketDisconnect) as closed:
                three.receive_json()
            assert closed.value.code == Close.FULL
        # Those inside go on.
        one.send_json({"type": "chat", "text": "still here"})
        while (message := two.receive_json())["type"] != "chat":
            pass
        assert message["item"]["text"] == "still here"
    with client.websocket_connect(path + "Three", headers=NOBODY) as three:
        assert three.receive_json()["type"] == "welcome"  # room empty again
