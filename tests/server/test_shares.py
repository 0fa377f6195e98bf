"""Share links: made by the owner, hashed at rest, opening exactly one model (or one
volume's models) without an account, expiring and revoked at once, and the provenance
that travels with the model."""

from __future__ import annotations

import gzip
import hashlib
import json
import struct
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from lxml import etree
from sqlalchemy import update

from miss.server.storage.db import ShareRow, utcnow


@pytest.fixture(scope="module")
def work(client: TestClient, people: dict, small_nifti: bytes, upload_for, model_for) -> dict:
    """alice's volume with two finished models, and another volume of hers."""
    alice = people["alice"]
    volume = upload_for(client, alice, small_nifti)
    first = model_for(client, alice, volume["id"], level=0)
    second = model_for(client, alice, volume["id"], level=500)
    other = upload_for(client, alice, small_nifti, "other.nii.gz")
    return {
        "alice": alice,
        "volume": volume,
        "model": first,
        "second": second,
        "other": model_for(client, alice, other["id"]),
    }


def anonymous(client: TestClient) -> TestClient:
    """Someone with the link and nothing else: no login, no cookie."""
    return TestClient(client.app)


def share(client: TestClient, headers: dict, **body: Any) -> dict:
    r = client.post("/api/shares", json=body, headers=headers)
    assert r.status_code == 201, r.text
    return r.json()


def expire(client: TestClient, share_id: str) -> None:
    """Move a link's expiry into the past (rather than wait a minute)."""
    store = client.app.state.store
    with store.session.begin() as s:
        past = utcnow() - timedelta(seconds=1)
        s.execute(update(ShareRow).where(ShareRow.id == share_id).values(expires_at=past))


def test_create_and_open_a_model_link(client: TestClient, work: dict) -> None:
    link = share(
        client, work["alice"], model=work["model"]["id"], expires_in=3600, label="Dr Lee",
        message="Left temporal bone, please",
    )  # fmt: skip
    assert link["url"].startswith("/s/") and link["shared_by"] == "alice"
    token = link["url"][3:]
    assert len(token) >= 22  # >= 128 random bits in URL-safe base64 (it is 256)
    # Stored hashed: the token itself is nowhere in the database file.
    db = Path(client.app.state.settings.data_dir, "miss.sqlite3")
    raw = b"".join(p.read_bytes() for p in db.parent.glob("miss.sqlite3*"))
    assert token.encode() not in raw
    assert hashlib.sha256(token.encode()).hexdigest().encode() in raw
    guest = anonymous(client)
    page = guest.get(link["url"])
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert page.headers["referrer-policy"] == "no-referrer"
    info = guest.get(f"{link['url']}/info").json()
    assert info["share"]["shared_by"] == "alice" and "label" not in info["share"]  # the owner's
    assert info["share"]["message"] == "Left temporal bone, please"
    assert info["share"]["expires"] == link["expires"] and "url" not in info["share"]
    (model,) = info["models"]
    assert model["id"] == work["model"]["id"] and list(model["files"]) == ["glb"]
    provenance = model["provenance"]
    assert provenance["software"].startswith("MISS ")
    assert provenance["source_sha256"] == info["volume"]["source_sha256"]
    assert len(provenance["source_sha256"]) == 64
    assert json.loads(provenance["parameters"])["level"] == 0
    glb = guest.get(model["files"]["glb"]["url"])
    assert glb.status_code == 200 and glb.content[:4] == b"glTF"
    assert glb.headers["cache-control"] == "no-store"
    assert guest.get(f"{link['url']}/model.glb").content == glb.content
    stl = guest.get(f"{link['url']}/model.stl")
    assert stl.status_code == 403 and "viewing only" in stl.json()["detail"]
    listed = client.get("/api/shares", headers=work["alice"]).json()
    assert link["id"] in [s["id"] for s in listed]
    assert all("url" not in s and "token" not in json.dumps(s) for s in listed)


def test_a_link_grants_exactly_what_it_says(client: TestClient, work: dict) -> None:
    link = share(client, work["alice"], model=work["model"]["id"], can_download=True)
    token = link["url"][3:]
    guest = anonymous(client)
    stl = guest.get(f"{link['url']}/model.stl")
    assert (
        stl.status_code == 200
        and len(stl.content) == 84 + 50 * struct.unpack_from("<I", stl.content, 80)[0]
    )
    # The other model of the same volume, another volume's model: not covered.
    for model in (work["second"], work["other"]):
        assert guest.get(f"{link['url']}/models/{model['id']}/model.glb").status_code == 404
    # The token opens no API route: no listing, no model, no upload.
    as_bearer = {"Authorization": f"Bearer {token}"}
    for method, path in (
        ("GET", "/api/volumes"),
        ("GET", f"/api/models/{work['model']['id']}"),
        ("GET", f"/api/models/{work['model']['id']}/model.glb"),
        ("GET", "/api/shares"),
        ("POST", "/api/volumes"),
    ):
        assert guest.request(method, path, headers=as_bearer).status_code == 401
    assert guest.get(f"/api/models/{work['model']['id']}/model.glb").status_code == 401
    assert guest.get("/s/not-a-real-token-at-all-0123456789").status_code == 404


def test_volume_link_covers_its_models(client: TestClient, work: dict) -> None:
    link = share(client, work["alice"], volume=work["volume"]["id"])
    guest = anonymous(client)
    info = guest.get(f"{link['url']}/info").json()
    assert {m["id"] for m in info["models"]} == {work["model"]["id"], work["second"]["id"]}
    for model in (work["model"], work["second"]):
        url = f"{link['url']}/models/{model['id']}/model.glb"
        assert guest.get(url).status_code == 200
    url = f"{link['url']}/models/{work['other']['id']}/model.glb"
    assert guest.get(url).status_code == 404


def test_expired_and_revoked_links_get_a_clear_page(client: TestClient, work: dict) -> None:
    guest = anonymous(client)
    for how in ("expired", "revoked"):
        link = share(client, work["alice"], model=work["model"]["id"])
        assert guest.get(f"{link['url']}/model.glb").status_code == 200
        if how == "expired":
            expire(client, link["id"])
        else:
            assert (
                client.delete(f"/api/shares/{link['id']}", headers=work["alice"]).status_code == 204
            )
        page = guest.get(link["url"])
        assert page.status_code == 410 and page.headers["content-type"].startswith("text/html")
        assert how in page.text and "Traceback" not in page.text
        assert "<title>MISS · This link is no longer valid</title>" in page.text
        info = guest.get(f"{link['url']}/info")
        assert info.status_code == 410 and how in info.json()["detail"]
        assert guest.get(f"{link['url']}/model.glb").status_code == 410
        listed = {s["id"]: s for s in client.get("/api/shares", headers=work["alice"]).json()}
        assert listed[link["id"]]["status"] == how
    unknown = guest.get("/s/AAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAA")
    assert unknown.status_code == 404 and "does not exist" in unknown.text


BAD_SHARES = [
    ({}, "exactly one"),
    ({"model": "MODEL", "volume": "VOLUME"}, "exactly one"),
    ({"model": "MODEL", "expires_in": 5}, "out of range"),
    ({"model": "MODEL", "expires_in": 10**9}, "out of range"),
    ({"model": "MODEL", "colour": "red"}, "colour"),
]


@pytest.mark.parametrize(("body", "words"), BAD_SHARES)
def test_bad_share_requests(client: TestClient, work: dict, body: dict, words: str) -> None:
    ids = {"MODEL": work["model"]["id"], "VOLUME": work["volume"]["id"]}
    body = {k: ids.get(v, v) if isinstance(v, str) else v for k, v in body.items()}
    r = client.post("/api/shares", json=body, headers=work["alice"])
    assert r.status_code == 422 and words in r.json()["detail"], r.text
    r = client.post("/api/shares", json={"model": "nope"}, headers=work["alice"])
    assert r.status_code == 404


def test_provenance_is_embedded_in_the_files(client: TestClient, work: dict) -> None:
    model_id = work["model"]["id"]
    model = client.get(f"/api/models/{model_id}", headers=work["alice"]).json()
    info_hash = model["stats"]["provenance"]["source_sha256"]
    glb = client.get(f"/api/models/{model_id}/model.glb", headers=work["alice"]).content
    (length,) = struct.unpack_from("<I", glb, 12)
    document = json.loads(glb[20 : 20 + length])
    extras = document["asset"]["extras"]
    assert extras["software"].startswith("MISS ") and extras["source_sha256"] == info_hash
    assert json.loads(extras["parameters"])["level"] == 0
    wrl = client.get(f"/api/models/{model_id}/model.wrl", headers=work["alice"]).text
    assert "WorldInfo" in wrl and info_hash in wrl
    wrz = client.get(f"/api/models/{model_id}/model.wrz", headers=work["alice"]).content
    assert info_hash.encode() in gzip.decompress(wrz)
    x3d = etree.fromstring(
        client.get(f"/api/models/{model_id}/model.x3d", headers=work["alice"]).content
    )
    metas = {m.get("name"): m.get("content") for m in x3d.iter("meta")}
    assert metas.get("source_sha256") == info_hash and metas["software"].startswith("MISS ")
