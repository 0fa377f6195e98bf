"""``miss user disable|passwd|revoke-pacs`` beside a running ``miss serve``: the server
drops what it cached of the account's logins at once, so the change counts within a
second, not when the cache's 30 s run out (the finding)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator

import httpx
import pytest
from support.pg import database_url
from support.realserver import Server, serving

PASSWORD = "a-good-long-password"
#: The change must count within a second; the poll allows a busy machine one more.
BOUND = 2.0


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    folder = tmp_path_factory.mktemp("changes")
    # A PACS that is never asked: listing the configured ones needs the permission only.
    env = {"MISS_DEMO": "0", "MISS_PACS_URL": "http://127.0.0.1:9/dicom-web"}
    with serving(folder / "data", folder / "server.log", env=env) as running:
        yield running


def user_with_login(server: Server, name: str, pacs: bool = False) -> httpx.Client:
    """A new account, logged in, whose session the server has read (and cached)."""
    body = {"name": name, "password": PASSWORD, "pacs": pacs}
    assert server.http.post("/api/users", json=body).status_code == 201
    r = httpx.post(
        f"{server.url}/api/auth/login", json={"username": name, "password": PASSWORD}, timeout=60
    )
    assert r.status_code == 200, r.text
    http = httpx.Client(
        base_url=server.url, headers={"Authorization": f"Bearer {r.json()['token']}"}, timeout=60
    )
    assert http.get("/api/auth/me").status_code == 200
    return http


def miss_user(server: Server, *args: str, stdin: str = "") -> None:
    """The real command line, on the server's data folder (and database)."""
    env = {**os.environ, "MISS_DATA_DIR": str(server.data_dir)}
    if url := database_url(server.data_dir):
        env["MISS_DATABASE_URL"] = url
    said = subprocess.run(
        [sys.executable, "-m", "miss.cli", "user", *args],
        input=stdin, capture_output=True, text=True, env=env, timeout=120,
    )  # fmt: skip
    assert said.returncode == 0, said.stderr


def refused_after(http: httpx.Client, path: str, codes: tuple[int, ...]) -> int:
    """Ask ``path`` until it answers one of ``codes``, at most ``BOUND`` seconds; the
    last status."""
    deadline = time.monotonic() + BOUND
    status = http.get(path).status_code
    while status not in codes and time.monotonic() < deadline:
        time.sleep(0.05)
        status = http.get(path).status_code
    return status


def test_disable_ends_the_logins_at_once(server: Server) -> None:
    http = user_with_login(server, "dis")
    miss_user(server, "disable", "dis")
    assert refused_after(http, "/api/auth/me", (401,)) == 401
    assert refused_after(http, "/api/volumes", (401,)) == 401


def test_a_new_password_ends_the_logins_at_once(server: Server) -> None:
    http = user_with_login(server, "pw")
    miss_user(server, "passwd", "pw", stdin="another-long-password\n")
    assert refused_after(http, "/api/auth/me", (401,)) == 401


def test_revoked_pacs_permission_counts_at_once(server: Server) -> None:
    http = user_with_login(server, "radiologist", pacs=True)
    assert http.get("/api/pacs").status_code == 200
    miss_user(server, "revoke-pacs", "radiologist")
    assert refused_after(http, "/api/pacs", (404,)) == 404
    assert http.get("/api/auth/me").json()["pacs"] is False  # the login itself goes on
    miss_user(server, "grant-pacs", "radiologist")
    assert refused_after(http, "/api/pacs", (200,)) == 200
