"""Shared with me: a signed-in colleague who opens a share link finds it again in
``GET /api/shared-with-me`` while it is valid; guests and owners leave no trace; each
account sees its own list; the owner is named, never identified by id. And the volume
list comes newest first, ties broken by id, so a reload keeps the order."""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select, update

from miss.server.accounts import find_user
from miss.server.storage.db import ShareOpeningRow, ShareRow, VolumeRow, utcnow


@pytest.fixture(scope="module")
def work(client: TestClient, people: dict, small_nifti: bytes, upload_for, model_for) -> dict:
    """alice's volume with a finished model, and carol, a third account."""
    alice = people["alice"]
    volume = upload_for(client, alice, small_nifti)
    model = model_for(client, alice, volume["id"])
    r = client.post("/api/users", json={"name": "carol", "password": "carol-password"})
    assert r.status_code == 201, r.text
    login = client.post(
        "/api/auth/login",
        json={"username": "carol", "password": "carol-password"},
        headers={"Authorization": ""},
    )
    client.cookies.clear()
    carol = {"Authorization": f"Bearer {login.json()['token']}"}
    return {"alice": alice, "bob": people["bob"], "carol": carol, "volume": volume, "model": model}


def link(client: TestClient, headers: dict, **body: Any) -> dict:
    r = client.post("/api/shares", json=body, headers=headers)
    assert r.status_code == 201, r.text
    return r.json()


def mine(client: TestClient, headers: dict) -> list[dict]:
    r = client.get("/api/shared-with-me", headers=headers)
    assert r.status_code == 200, r.text
    return r.json()


def openings_of(client: TestClient, share_id: str) -> list[str]:
    """The user ids that have opened ``share_id`` (read from the table itself)."""
    with client.app.state.store.session() as s:
        query = select(ShareOpeningRow.user_id).where(ShareOpeningRow.share_id == share_id)
        return list(s.scalars(query))


def test_opening_a_link_signed_in_lists_it(client: TestClient, work: dict) -> None:
    url = link(
        client, work["alice"], model=work["model"]["id"], can_annotate=True,
        message="Have a look at the left side",
    )  # fmt: skip
    share_id = url["id"]
    assert client.get(url["url"], headers=work["bob"]).status_code == 200
    (entry,) = [e for e in mine(client, work["bob"]) if e["id"] == share_id]
    assert entry["shared_by"] == "alice" and entry["kind"] == "model"
    assert entry["name"] == work["volume"]["name"] == entry["volume_name"]
    assert entry["allows"] == ["view", "annotate"]
    assert entry["message"] == "Have a look at the left side"
    assert datetime.fromisoformat(entry["opened"]).utcoffset() == timedelta(0)
    # The owner's account id is nowhere in the answer.
    alice_id = find_user(client.app.state.store, "alice").id
    assert alice_id not in client.get("/api/shared-with-me", headers=work["bob"]).text
    # carol has her own list: bob's opening is not in it until she opens the link too.
    assert share_id not in [e["id"] for e in mine(client, work["carol"])]
    assert client.get(f"{url['url']}/info", headers=work["carol"]).status_code == 200
    assert share_id in [e["id"] for e in mine(client, work["carol"])]


def test_guests_and_the_owner_leave_no_opening(client: TestClient, work: dict) -> None:
    made = link(client, work["alice"], model=work["model"]["id"])
    guest = TestClient(client.app)  # the link and nothing else: no account
    assert guest.get(made["url"]).status_code == 200
    assert guest.get(f"{made['url']}/info").status_code == 200
    assert client.get(made["url"], headers=work["alice"]).status_code == 200
    assert openings_of(client, made["id"]) == []
    assert made["id"] not in [e["id"] for e in mine(client, work["alice"])]
    assert guest.get("/api/shared-with-me").status_code == 401


def test_the_latest_opened_comes_first(client: TestClient, work: dict) -> None:
    first = link(client, work["alice"], volume=work["volume"]["id"], can_download=True)
    second = link(client, work["alice"], model=work["model"]["id"])
    client.get(first["url"], headers=work["bob"])
    client.get(second["url"], headers=work["bob"])
    ids = [e["id"] for e in mine(client, work["bob"])]
    assert ids.index(second["id"]) < ids.index(first["id"])
    client.get(f"{first['url']}/info", headers=work["bob"])  # opened again: now the latest
    listed = mine(client, work["bob"])
    assert listed[0]["id"] == first["id"]
    assert listed[0]["kind"] == "volume" and listed[0]["allows"] == ["view", "download"]
    assert openings_of(client, first["id"]).count(find_user(client.app.state.store, "bob").id) == 1


def test_revoked_expired_and_deleted_links_leave_the_list(
    client: TestClient, work: dict, small_nifti: bytes, upload_for, model_for
) -> None:
    revoked = link(client, work["alice"], model=work["model"]["id"])
    expired = link(client, work["alice"], model=work["model"]["id"])
    other = upload_for(client, work["alice"], small_nifti, "gone.nii.gz")
    gone = link(client, work["alice"], model=model_for(client, work["alice"], other["id"])["id"])
    for made in (revoked, expired, gone):
        assert client.get(made["url"], headers=work["bob"]).status_code == 200
    assert {revoked["id"], expired["id"], gone["id"]} <= {
        e["id"] for e in mine(client, work["bob"])
    }
    r = client.delete(f"/api/shares/{revoked['id']}", headers=work["alice"])
    assert r.status_code == 204
    with client.app.state.store.session.begin() as s:
        past = utcnow() - timedelta(seconds=1)
        s.execute(update(ShareRow).where(ShareRow.id == expired["id"]).values(expires_at=past))
    r = client.delete(f"/api/volumes/{other['id']}", headers=work["alice"])
    assert r.status_code == 204, r.text
    left = {e["id"] for e in mine(client, work["bob"])}
    assert not left & {revoked["id"], expired["id"], gone["id"]}


def test_volumes_come_newest_first_ties_by_id(
    client: TestClient, work: dict, small_nifti: bytes, upload_for
) -> None:
    older = upload_for(client, work["bob"], small_nifti, "older.nii.gz")
    newer = upload_for(client, work["bob"], small_nifti, "newer.nii.gz")
    listed = [v["id"] for v in client.get("/api/volumes", headers=work["bob"]).json()]
    assert listed == [newer["id"], older["id"]]
    # Stored within one tick of the clock: the larger id first, every time.
    with client.app.state.store.session.begin() as s:
        same = utcnow()
        query = update(VolumeRow).where(VolumeRow.id.in_(listed)).values(created_at=same)
        s.execute(query)
    listed = [v["id"] for v in client.get("/api/volumes", headers=work["bob"]).json()]
    assert listed == sorted(listed, reverse=True)
