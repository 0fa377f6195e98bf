"""Browser-test fixtures: a real ``miss serve`` on a free loopback port and Debian's chromium.

The server runs as a subprocess with its own temporary data folder, exactly as a
user starts it; the pages are driven through Playwright (Python) with the system
chromium, never a browser that Playwright downloads.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from support import ADMIN_PASSWORD, REPO
from support.realserver import Server, serving

ARTIFACTS = REPO / "test-artifacts" / "browser"
CHROMIUM = Path(os.environ.get("MISS_CHROMIUM", "/usr/bin/chromium"))
# Headless chromium with no GPU draws WebGL through SwiftShader (software).
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
LAPTOP = {"width": 1366, "height": 768}

if not CHROMIUM.is_file():
    pytest.skip(
        f"browser tests need Debian's chromium at {CHROMIUM} (`make chromium` installs it)",
        allow_module_level=True,
    )
sync_api = pytest.importorskip("playwright.sync_api", reason="Playwright (Python) is not installed")


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """``miss serve`` on a free 127.0.0.1 port with an empty temporary data folder."""
    with serve(tmp_path_factory) as running:
        yield running


def serve(tmp_path_factory: pytest.TempPathFactory, **settings: str) -> Any:
    """A ``miss serve`` of its own, logged in, with ``settings`` (``MISS_...`` variables)
    in its environment and the server's own worker count: for tests that need other
    settings than the session's server. A context manager giving a :class:`Server`."""
    data_dir = tmp_path_factory.mktemp("miss-data")
    log = data_dir.parent / f"{data_dir.name}-serve.log"
    env = {"MISS_DATA_DIR": str(data_dir), **settings}
    return serving(data_dir, log, workers=None, env=env, args=["--host", "127.0.0.1"])


@pytest.fixture(scope="session")
def artifacts() -> Path:
    """Folder for screenshots (git-ignored); look at them after a run."""
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    return ARTIFACTS


def log_in_context(context: Any, name: str = "admin", password: str = ADMIN_PASSWORD) -> None:
    """Log a browser context in as the login page would: the session cookies land in it."""
    response = context.request.post(
        "/api/auth/login", data={"username": name, "password": password}
    )
    assert response.status == 200, response.text()


@pytest.fixture(scope="session")
def logged_in() -> Any:
    """``logged_in(context)``: the context now carries an admin session."""
    return log_in_context


@pytest.fixture
def page(browser: Any, server: Server) -> Iterator[Any]:
    """A laptop-sized page (1366x768), logged in, whose script errors fail the test."""
    with laptop_page(browser, server) as opened:
        yield opened


@contextlib.contextmanager
def laptop_page(browser: Any, server: Server) -> Iterator[Any]:
    """The ``page`` fixture's page on any server (see :func:`serve`)."""
    context = browser.new_context(viewport=LAPTOP, accept_downloads=True, base_url=server.url)
    log_in_context(context)
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(f"page error: {exc}"))
    page.on(
        "console",
        lambda msg: errors.append(f"console: {msg.text}") if msg.type == "error" else None,
    )
    page.set_default_timeout(30_000)
    try:
        yield page
    finally:
        context.close()
    assert not errors, "the page logged errors:\n" + "\n".join(errors)


#: The page's room is open and knows who this browser is.
ROOM_CONNECTED = (
    "() => window.__miss.room && window.__miss.room.connected && !!window.__miss.room.you"
)


@contextlib.contextmanager
def owner_and_guest(page: Any, browser: Any, server: Server, model_id: str) -> Iterator[Any]:
    """The owner's ``page`` on the model and a guest's page, in another browser context, on a
    new link to it that offers the scan and the room; both in the room when it yields the
    guest's page."""
    link = server.post(
        "/api/shares",
        {"model": model_id, "expires_in": 3600, "can_view_volume": True, "can_annotate": True},
    )["url"]
    page.goto(f"/models/{model_id}")
    page.wait_for_function("() => window.__miss.ready === true")
    page.wait_for_function(ROOM_CONNECTED)
    context = browser.new_context(viewport=LAPTOP, base_url=server.url)
    try:
        guest = context.new_page()
        guest.goto(link)
        guest.wait_for_function("() => window.__miss.ready === true")
        guest.wait_for_function(ROOM_CONNECTED)
        yield guest
    finally:
        context.close()


@pytest.fixture(scope="session")
def phantom(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The synthetic CT head as NIfTI, written by the CLI as a user would."""
    path = tmp_path_factory.mktemp("upload") / "phantom-head.nii.gz"
    subprocess.run(
        [sys.executable, "-m", "miss.cli", "demo", str(path)], check=True, capture_output=True
    )
    return path
