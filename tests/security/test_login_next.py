"""Where the login sends a browser afterwards (``next``): a path on this server, however
``next`` is spelled. The finding: ``/login?next=/.//evil.example/phish`` (and ``/%2e//``,
``/a/..//``) passed the page's own check and landed on another host, because the browser
removes dot segments and what remains, ``//evil.example/phish``, names a host. One rule
decides now, on the URL as a browser resolves it (``miss.server.core.nextpath``), and the
page goes where the login's answer says. chromium's verdict on the same spellings:
``tests/browser/test_login_next_page.py``."""

from __future__ import annotations

import re
from urllib.parse import parse_qs, quote, urlsplit

import pytest
from fastapi.testclient import TestClient
from support import ADMIN_PASSWORD

#: Spellings that lead off the server in some browser, or are no path at all: "/".
OFFSITE = [
    "/.//evil.example/phish",
    "/%2e//evil.example/phish",
    "/%2E//evil.example/phish",
    "/a/..//evil.example/phish",
    "/a/%2e%2e//evil.example",
    "/a/.%2E//evil.example",
    "/a/%2e.//evil.example",
    "/..//evil.example",
    "/../..//evil.example",
    "/.\\/evil.example",
    "/./\\evil.example",
    "/a/..\\\\evil.example",
    "//evil.example",
    "///evil.example",
    "/\\evil.example",
    "\\\\evil.example",
    "\\/evil.example",
    "/\t/evil.example",
    "/\n/evil.example",
    "/\r\n/evil.example",
    "\t//evil.example",
    " //evil.example",
    "\x00//evil.example",
    "/.\t/\t/evil.example",
    "https://evil.example/",
    "HTTPS://evil.example",
    "http:evil.example",
    "http:/evil.example",
    "http:\\\\evil.example",
    "javascript:alert(1)",
    "JaVaScRiPt:alert(1)",
    "java\tscript:alert(1)",
    "data:text/html,<script>alert(1)</script>",
    "evil.example",
    "./evil.example",
    "?//evil.example",
    "#//evil.example",
    "",
    "/" + "a" * 3000,
]

#: Paths on this server, and what they become (dot segments resolved, odd characters
#: percent-encoded as a browser would, backslashes read as slashes).
ONSITE = {
    "/": "/",
    "/volumes/abc": "/volumes/abc",
    "/models/x?view=1&a=b#top": "/models/x?view=1&a=b#top",
    "/a/../volumes/y": "/volumes/y",
    "/./%2F/evil.example/phish": "/%2F/evil.example/phish",
    "/%2F%2Fevil.example": "/%2F%2Fevil.example",
    "/%5Cevil.example": "/%5Cevil.example",
    "/..;/evil.example": "/..;/evil.example",
    "/@evil.example": "/@evil.example",
    "/a\\b\\c": "/a/b/c",
    "/a b": "/a%20b",
    "/\uff0fevil.example": "/%EF%BC%8Fevil.example",
    "/%252e//evil.example": "/%252e//evil.example",
    "/a/..": "/",
    "/a/.": "/a/",
}

#: A path is on this server when it starts with one "/" followed by a character that
#: is neither "/" nor "\\", and holds no control character, space or backslash.
ON_THIS_SERVER = re.compile(r"/(?![/\\])[^\x00-\x20\x7f\\]*\Z")


@pytest.mark.parametrize("target", OFFSITE)
def test_offsite_spellings_lead_home(target: str) -> None:
    from miss.server.core.nextpath import safe_next

    assert safe_next(target) == "/"


@pytest.mark.parametrize(("target", "path"), ONSITE.items())
def test_paths_here_are_kept(target: str, path: str) -> None:
    from miss.server.core.nextpath import safe_next

    assert safe_next(target) == path
    assert ON_THIS_SERVER.match(path) and safe_next(path) == path  # a fixed point


@pytest.fixture(scope="module")
def app(client: TestClient) -> TestClient:
    return client


def final_next(app: TestClient, target: str) -> str:
    """The ``next`` the login page is served with, after the server's redirect."""
    r = app.get(f"/login?next={quote(target, safe='')}", follow_redirects=False)
    if r.status_code == 200:
        return target
    assert r.status_code == 303, r.text
    location = urlsplit(r.headers["location"])
    assert location.path == "/login" and not location.netloc, r.headers["location"]
    (kept,) = parse_qs(location.query)["next"]
    return kept


@pytest.mark.parametrize("target", OFFSITE[:-2] + list(ONSITE))
def test_the_page_and_the_login_answer_agree(app: TestClient, target: str) -> None:
    """The login page is served only with a ``next`` that stays here; the login's answer
    names the same place, and the page goes there."""
    served = final_next(app, target)
    assert ON_THIS_SERVER.match(served), served
    assert served == ("/" if target in OFFSITE else ONSITE[target])
    body = {"username": "admin", "password": ADMIN_PASSWORD, "next": target}
    r = app.post("/api/auth/login", json=body, headers={"Authorization": ""})
    assert r.status_code == 200, r.text
    assert r.json()["next"] == served
