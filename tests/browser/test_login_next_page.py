"""The login page in chromium, with ``next`` spelled every way we know of: after logging
in, the browser is on this server. And the rule the server applies
(``miss.server.core.nextpath.safe_next``) agrees with chromium's own URL parser: what it
accepts, chromium resolves to this server and to the same path; whatever chromium
resolves to another host, it refuses."""

from __future__ import annotations

import time
from typing import Any
from urllib.parse import quote, urlsplit

from support import ADMIN_PASSWORD
from support.realserver import Server
from test_security_pages import offline_context

EVIL = "evil.example"
SPELLINGS = [
    f"/.//{EVIL}/phish",
    f"/%2e//{EVIL}/phish",
    f"/%2E//{EVIL}/phish",
    f"/a/..//{EVIL}/phish",
    f"/./%2F/{EVIL}/phish",
    f"/a/%2e%2e//{EVIL}",
    f"/a/.%2E//{EVIL}",
    f"/..//{EVIL}",
    f"/../..//{EVIL}",
    f"/.\\/{EVIL}",
    f"/./\\{EVIL}",
    f"/a/..\\\\{EVIL}",
    f"//{EVIL}",
    f"///{EVIL}",
    f"/\\{EVIL}",
    f"\\\\{EVIL}",
    f"\\/{EVIL}",
    f"/\t/{EVIL}",
    f"/\n/{EVIL}",
    f"/.\t/\t/{EVIL}",
    f"\t//{EVIL}",
    f" //{EVIL}",
    f"/%09/{EVIL}",
    f"/%0a/{EVIL}",
    f"/%5C{EVIL}",
    f"/%5C%5C{EVIL}",
    f"/%2F%2F{EVIL}",
    f"/%2f/{EVIL}",
    f"/%252e//{EVIL}",
    f"https://{EVIL}/",
    f"HTTPS://{EVIL}",
    f"http:{EVIL}",
    f"http:/{EVIL}",
    f"http:\\\\{EVIL}",
    f"//{EVIL}@127.0.0.1",
    f"/@{EVIL}",
    "javascript:alert(1)",
    "JaVaScRiPt:alert(1)",
    "java\tscript:alert(1)",
    "data:text/html,<script>alert(1)</script>",
    f"/..;/{EVIL}",
    f"/..;//{EVIL}",
    f"/\uff0f{EVIL}",
    f"/ /{EVIL}",
    EVIL,
    f"?//{EVIL}",
    "/volumes/abc?x=1#y",
    "/a/../volumes/b",
]

RESOLVE = """([values, base]) => values.map((value) => {
    try {
        const url = new URL(value, base);
        return [url.origin, url.pathname + url.search + url.hash];
    } catch { return null; }
})"""


def test_the_rule_agrees_with_chromium(browser: Any, server: Server) -> None:
    from miss.server.core.nextpath import safe_next

    page = browser.new_page()
    page.goto(server.url + "/login")
    base = server.url + "/login"
    raw = page.evaluate(RESOLVE, [SPELLINGS, base])
    checked = [safe_next(s) for s in SPELLINGS]
    again = page.evaluate(RESOLVE, [checked, server.url + "/"])
    page.close()
    for spelling, (origin, path), kept, (kept_origin, kept_path) in zip(
        SPELLINGS, [r or ("null", "") for r in raw], checked, again, strict=True
    ):
        if origin != server.url or path.startswith("//"):
            assert kept == "/", (spelling, origin, path, kept)
        assert kept_origin == server.url and kept_path == kept, (spelling, kept, kept_path)


def logged_in_from(browser: Any, server: Server, query: str) -> tuple[str, list[str]]:
    """Log in on ``/login?next=<query>`` as a person does: (where the page ended up,
    requests to any other origin)."""
    context, elsewhere = offline_context(browser, server)
    page = context.new_page()
    page.goto(f"/login?next={query}")
    page.fill("#username", "admin")
    page.fill("#password", ADMIN_PASSWORD)
    page.click("#submit")
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and not elsewhere:
        if not urlsplit(page.url).path.startswith("/login"):
            break
        page.wait_for_timeout(100)
    page.wait_for_load_state()
    landed = page.url
    context.close()
    return landed, elsewhere


def test_the_login_page_stays_on_this_server(browser: Any, server: Server) -> None:
    """The finding: ``/login?next=/.//evil.example/phish`` landed on evil.example. Each
    spelling both as the value (encoded) and as typed into the address bar."""
    wrong = []
    for spelling in SPELLINGS:
        for query in {quote(spelling, safe=""), spelling.replace("#", "%23")}:
            landed, elsewhere = logged_in_from(browser, server, query)
            parts = urlsplit(landed)
            if f"{parts.scheme}://{parts.netloc}" != server.url or elsewhere:
                wrong.append((query, landed, elsewhere))
            elif parts.path.startswith("/login"):
                wrong.append((query, landed, "still on the login page"))
    assert wrong == [], wrong
