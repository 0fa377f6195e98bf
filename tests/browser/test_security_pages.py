"""The pages under the Content-Security-Policy, as a person meets them in chromium: the
API documentation loads from this server alone, and the login never sends anyone to
another host, however ``next`` is spelled."""

from __future__ import annotations

from typing import Any
from urllib.parse import quote, urlsplit

import pytest
from browser.conftest import LAPTOP
from support import ADMIN_PASSWORD
from support.realserver import Server

#: ReDoc's menu footer asks for its maker's logo from a CDN; the CSP blocks it (nothing
#: leaves the machine) and the console says so. Nothing else may be refused.
REDOC_LOGO = "cdn.redoc.ly/redoc/logo-mini.svg"


def offline_context(browser: Any, server: Server) -> tuple[Any, list[str]]:
    """A context whose requests to any origin but the server's are aborted (and listed)."""
    context = browser.new_context(viewport=LAPTOP, base_url=server.url)
    elsewhere: list[str] = []

    def only_the_server(route: Any) -> None:
        url = route.request.url
        if url.startswith((server.url, "data:", "blob:")):
            route.continue_()
        else:
            elsewhere.append(url)
            route.abort()

    context.route("**/*", only_the_server)
    return context, elsewhere


@pytest.mark.parametrize(("path", "shows"), [("/docs", "/api/volumes"), ("/redoc", "/api/volumes")])
def test_api_docs_load_with_only_the_server_reachable(
    browser: Any, server: Server, artifacts: Any, path: str, shows: str
) -> None:
    context, elsewhere = offline_context(browser, server)
    page = context.new_page()
    console: list[str] = []
    page.on("console", lambda m: console.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: console.append(f"page error: {e}"))
    page.goto(path)
    page.get_by_text("Upload Volume").first.wait_for(state="attached", timeout=30_000)
    assert shows in page.inner_text("body")
    page.screenshot(path=str(artifacts / f"docs{path.replace('/', '-')}.png"))
    context.close()
    assert elsewhere == [], f"{path} reached for other origins: {elsewhere}"
    assert [m for m in console if REDOC_LOGO not in m] == [], console


NEXT = [
    "/%5Cevil.example",
    "/%09/evil.example",
    "//evil.example",
    "/\\evil.example",
    "https://evil.example/",
    "javascript:alert(1)",
    "/%2F%2Fevil.example",
    "/\uff0fevil.example",
    "\\\\evil.example",
    "/ /evil.example",
    "/" + "a" * 3000,
]


@pytest.mark.parametrize("nxt", NEXT)
def test_login_stays_on_this_server(browser: Any, server: Server, nxt: str) -> None:
    """The finding: /login?next=/%5Cevil.example (and /%09/...) landed on another host."""
    context, elsewhere = offline_context(browser, server)
    page = context.new_page()
    query = nxt if nxt.startswith("/%") else quote(nxt, safe="")
    page.goto(f"/login?next={query}")
    page.fill("#username", "admin")
    page.fill("#password", ADMIN_PASSWORD)
    page.click("#submit")
    page.wait_for_function("() => !location.pathname.startsWith('/login')", timeout=30_000)
    page.wait_for_load_state()
    landed = urlsplit(page.url)
    context.close()
    assert f"{landed.scheme}://{landed.netloc}" == server.url, page.url
    assert elsewhere == [], elsewhere
