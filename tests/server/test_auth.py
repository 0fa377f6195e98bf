"""Accounts: login, bearer tokens and the session cookie with its CSRF check, owners who
see only their own things, the audit log, ``miss user add`` and ``miss audit``."""

from __future__ import annotations

import io
import json
import sqlite3
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from miss.cli import main as cli
from miss.server.app import create_app
from miss.server.core.deps import get_login_limits
from miss.server.core.ratelimit import LoginLimits
from miss.server.core.settings import Settings

PUBLIC = {"/api/auth/login", "/api/health"}


def anonymous(client: TestClient) -> TestClient:
    """A client of the same running app with no credentials (no lifespan of its own)."""
    return TestClient(client.app)


def test_every_api_route_needs_login(client: TestClient) -> None:
    anon = anonymous(client)
    checked = 0
    for path, operations in client.get("/openapi.json").json()["paths"].items():
        if path in PUBLIC or not path.startswith("/api/"):
            continue
        path = path.replace("{fmt}", "glb").replace("{axis}", "axial").replace("{index}", "1")
        for key in ("volume_id", "model_id", "share_id"):
            path = path.replace("{" + key + "}", "x")
        for method in operations:
            r = anon.request(method.upper(), path, json={})
            assert r.status_code == 401, (method, path, r.status_code, r.text)
            assert "log in" in r.json()["detail"]
            assert r.headers["www-authenticate"].startswith("Bearer")
            checked += 1
    assert checked >= 20
    assert anon.get("/api/health").status_code == 200


def test_login_bearer_logout(client: TestClient, admin_password: str) -> None:
    anon = anonymous(client)
    for name, password in (("admin", "wrong-password"), ("nobody", admin_password)):
        r = anon.post("/api/auth/login", json={"username": name, "password": password})
        assert r.status_code == 401 and r.json()["detail"] == "wrong user name or password."
    r = anon.post("/api/auth/login", json={"username": "admin", "password": admin_password})
    assert r.status_code == 200 and r.headers["cache-control"] == "no-store"
    body = r.json()
    assert len(body["token"]) >= 43 and body["user"] == {**body["user"], "name": "admin"}
    token = {"Authorization": f"Bearer {body['token']}"}
    anon.cookies.clear()
    assert anon.get("/api/auth/me", headers=token).json()["admin"] is True
    assert anon.post("/api/auth/logout", headers=token).status_code == 204
    assert anon.get("/api/auth/me", headers=token).status_code == 401  # ended at once
    bad = anon.get("/api/volumes", headers={"Authorization": "Bearer not-a-token"})
    assert bad.status_code == 401 and "expired" in bad.json()["detail"]
    # The body must be JSON: a cross-site HTML form cannot send that.
    form = anon.post("/api/auth/login", data={"username": "admin", "password": admin_password})
    assert form.status_code in (415, 422)


def test_session_cookie_and_csrf(client: TestClient, admin_password: str) -> None:
    browser = anonymous(client)
    r = browser.post("/api/auth/login", json={"username": "admin", "password": admin_password})
    cookies = r.headers.get_list("set-cookie")
    session = next(c for c in cookies if c.startswith("miss_session="))
    csrf_cookie = next(c for c in cookies if c.startswith("miss_csrf="))
    assert "HttpOnly" in session and "SameSite=lax" in session and "Path=/" in session
    assert "HttpOnly" not in csrf_cookie  # the pages must read it
    csrf = browser.cookies["miss_csrf"]
    assert browser.get("/api/volumes").status_code == 200  # reads need no token
    body = {"volume": "nope", "level": 1}
    r = browser.post("/api/models", json=body)
    assert r.status_code == 403 and "X-CSRF-Token" in r.json()["detail"]
    assert (
        browser.post("/api/models", json=body, headers={"X-CSRF-Token": "wrong"}).status_code == 403
    )
    ok = browser.post("/api/models", json=body, headers={"X-CSRF-Token": csrf})
    assert ok.status_code == 404  # past the CSRF check, to the (missing) volume
    foreign = {"X-CSRF-Token": csrf, "Origin": "http://evil.example"}
    assert browser.post("/api/models", json=body, headers=foreign).status_code == 403
    same = {"X-CSRF-Token": csrf, "Origin": "http://testserver"}
    assert browser.post("/api/models", json=body, headers=same).status_code == 404
    assert browser.post("/api/auth/logout").status_code == 403  # logout is a write too
    assert browser.post("/api/auth/logout", headers={"X-CSRF-Token": csrf}).status_code == 204
    assert browser.get("/api/volumes").status_code == 401


def test_pages_redirect_to_login(client: TestClient) -> None:
    anon = anonymous(client)
    for path in ("/", "/volumes/x", "/models/x"):
        r = anon.get(path, follow_redirects=False)
        assert r.status_code == 303 and r.headers["location"].startswith("/login?next=")
    assert anon.get("/login").status_code == 200


@pytest.mark.slow  # a dozen password hashes
def test_failed_logins_are_rate_limited(make_client) -> None:
    c = make_client()
    fresh = LoginLimits()  # no attempt counted yet
    c.app.dependency_overrides[get_login_limits] = lambda: fresh
    wrong = {"username": "admin", "password": "guess-guess"}
    codes = [c.post("/api/auth/login", json=wrong).status_code for _ in range(12)]
    assert codes[:10] == [401] * 10 and codes[10:] == [429, 429]
    refused = c.post("/api/auth/login", json=wrong)
    assert "too many failed logins" in refused.json()["detail"]
    assert int(refused.headers["retry-after"]) >= 1


def test_owners_see_only_their_own(
    client: TestClient, people: dict, upload_for, model_for, demo_id: str, small_nifti: bytes
) -> None:
    alice, bob = people["alice"], people["bob"]
    volume = upload_for(client, alice, small_nifti)
    assert volume["owner"] == "alice"
    vid, mid = volume["id"], model_for(client, alice, volume["id"])["id"]
    share = client.post("/api/shares", json={"model": mid}, headers=alice).json()
    assert vid in [v["id"] for v in client.get("/api/volumes", headers=alice).json()]
    listed = [v["id"] for v in client.get("/api/volumes", headers=bob).json()]
    assert vid not in listed and demo_id not in listed  # the demo is the admin's
    assert mid not in [m["id"] for m in client.get("/api/models", headers=bob).json()]
    assert client.get("/api/shares", headers=bob).json() == []
    hidden = [
        ("GET", f"/api/volumes/{vid}"),
        ("GET", f"/api/volumes/{vid}/histogram"),
        ("GET", f"/api/volumes/{vid}/thumbnail.png"),
        ("GET", f"/api/volumes/{vid}/slices/axial/3.png"),
        ("GET", f"/api/volumes/{vid}/identity"),
        ("GET", f"/api/models?volume={vid}"),
        ("GET", f"/api/models/{mid}"),
        ("GET", f"/api/models/{mid}/model.glb"),
        ("GET", f"/api/models/{mid}/events"),
        ("GET", f"/api/models/{mid}/room/events"),
        ("GET", f"/api/models/{mid}/room/sessions"),
        ("DELETE", f"/api/shares/{share['id']}"),
        ("DELETE", f"/api/models/{mid}"),
        ("DELETE", f"/api/volumes/{vid}"),
    ]
    for method, path in hidden:
        r = client.request(method, path, headers=bob)
        assert r.status_code == 404, (method, path, r.text)  # as if it did not exist
        assert "alice" not in r.text
    for body in ({"volume": vid, "level": 0}, {"model": mid}):
        url = "/api/models" if "level" in body else "/api/shares"
        assert client.post(url, json=body, headers=bob).status_code == 404
    # Nothing of alice's was touched; the administrator sees everything.
    assert client.get(f"/api/models/{mid}", headers=alice).status_code == 200
    assert client.get(f"/api/models/{mid}").status_code == 200
    assert vid in [v["id"] for v in client.get("/api/volumes").json()]
    assert client.get(f"/api/volumes/{vid}/identity").status_code == 404  # the owner's only


def test_audit_records_who_what_when_where(
    client: TestClient, people: dict, upload_for, model_for, small_nifti: bytes
) -> None:
    alice = people["alice"]
    volume = upload_for(client, alice, small_nifti)
    model = model_for(client, alice, volume["id"], level=100)
    assert client.get(f"/api/models/{model['id']}/model.stl", headers=alice).status_code == 200
    assert client.get(f"/models/{model['id']}", headers=alice).status_code == 200
    share = client.post("/api/shares", json={"model": model["id"]}, headers=alice).json()
    assert client.delete(f"/api/shares/{share['id']}", headers=alice).status_code == 204
    entries = client.get("/api/audit", params={"actor": "alice"}).json()
    done = {(e["action"], e["target"]) for e in entries}
    expected = {
        ("upload", volume["id"]),
        ("generate", model["id"]),
        ("download", model["id"]),
        ("view", model["id"]),
        ("share", model["id"]),
        ("revoke", share["id"]),
    }
    assert expected <= done and ("login", "") in done
    assert all(e["address"] == "testclient" and e["at"].endswith("+00:00") for e in entries)
    shares = client.get("/api/audit", params={"action": "share"}).json()
    assert shares and {e["action"] for e in shares} == {"share"}
    assert "bob" not in {e["actor"] for e in shares}


def test_admin_only_routes(client: TestClient, people: dict) -> None:
    for path in ("/api/audit", "/api/users"):
        r = client.get(path, headers=people["alice"])
        assert r.status_code == 403 and "administrators" in r.json()["detail"]
        assert client.get(path).status_code == 200
    r = client.post("/api/users", json={"name": "eve", "password": "x" * 8}, headers=people["bob"])
    assert r.status_code == 403
    r = client.post("/api/users", json={"name": "alice", "password": "another-pass"})
    assert r.status_code == 422 and "exists already" in r.json()["detail"]
    r = client.post("/api/users", json={"name": "carol", "password": "short"})
    assert r.status_code == 422 and "at least 8" in r.json()["detail"]


def test_cli_user_add_and_audit(
    client: TestClient, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    data = str(client.app.state.settings.data_dir)
    monkeypatch.setattr("sys.stdin", io.StringIO("dana-password\n"))
    assert cli(["user", "add", "dana", "--data-dir", data]) == 0
    assert "created user 'dana'" in capsys.readouterr().out
    anon = anonymous(client)
    r = anon.post("/api/auth/login", json={"username": "dana", "password": "dana-password"})
    assert r.status_code == 200 and r.json()["user"]["admin"] is False
    monkeypatch.setattr("sys.stdin", io.StringIO("dana-password\n"))
    assert cli(["user", "add", "dana", "--data-dir", data]) == 2
    assert "exists already" in capsys.readouterr().err
    assert cli(["audit", "--data-dir", data, "--action", "login"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert any("dana" in line and "login" in line and "testclient" in line for line in lines)
    assert cli(["audit", "--data-dir", data, "--json", "--limit", "3"]) == 0
    entries = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert len(entries) == 3 and {"at", "actor", "action", "address"} <= set(entries[0])
    assert Path(data, "miss.sqlite3").is_file()


def test_a_data_folder_from_before_accounts_is_taken_over(tmp_path: Path, login) -> None:
    """An older database (volumes without owners, no user tables) gains the new columns
    and tables, and its volumes go to the first administrator."""
    data = tmp_path / "data"
    data.mkdir()
    with sqlite3.connect(data / "miss.sqlite3") as db:
        db.execute(
            "CREATE TABLE volumes (id VARCHAR(32) PRIMARY KEY, name VARCHAR(200), "
            "slug VARCHAR(64), created_at DATETIME, info JSON)"
        )
        db.execute(
            "INSERT INTO volumes VALUES ('old', 'Old scan', 'old-scan', '2024-01-01 00:00:00', "
            '\'{"units": ""}\')'
        )
    (data / "volumes" / "old").mkdir(parents=True)
    settings = Settings(data_dir=data, demo=False, admin_password="first-admin-password")
    with TestClient(create_app(settings)) as c:
        login(c, "admin", "first-admin-password")
        assert c.app.state.store.get_volume("old").owner_id is not None
        assert [v.name for v in c.app.state.store.list_volumes()] == ["Old scan"]
