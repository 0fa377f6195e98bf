"""Browser-test fixtures: a real ``miss serve`` on a free loopback port and Debian's chromium.

The server runs as a subprocess with its own temporary data folder, exactly as a
user starts it; the pages are driven through Playwright (Python) with the system
chromium, never a browser that Playwright downloads.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[2]
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
STARTUP_SECONDS = 90
ADMIN_PASSWORD = "admin-password-for-browsers"

if not CHROMIUM.is_file():
    pytest.skip(
        f"browser tests need Debian's chromium at {CHROMIUM} (`make chromium` installs it)",
        allow_module_level=True,
    )
sync_api = pytest.importorskip("playwright.sync_api", reason="Playwright (Python) is not installed")


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Server:
    """A running ``miss serve``: its base URL and a tiny JSON client for setting up tests."""

    def __init__(self, url: str, data_dir: Path, log: Path) -> None:
        self.url = url
        self.data_dir = data_dir
        self.log = log
        self.token = ""

    def log_in(self, name: str = "admin", password: str = ADMIN_PASSWORD) -> str:
        """A bearer token for this helper's own requests (as a script would log in)."""
        body = {"username": name, "password": password}
        self.token = self.post("/api/auth/login", body)["token"]
        return self.token

    def _send(self, path: str, body: dict[str, Any] | None, method: str) -> Any:
        headers = {"Content-Type": "application/json"}
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        data = json.dumps(body).encode() if body is not None else None
        request = urllib.request.Request(self.url + path, data=data, headers=headers, method=method)
        with urllib.request.urlopen(request, timeout=30) as response:
            text = response.read()
        return json.loads(text) if text else None

    def get(self, path: str) -> Any:
        return self._send(path, None, "GET")

    def post(self, path: str, body: dict[str, Any]) -> Any:
        return self._send(path, body, "POST")

    def delete(self, path: str) -> Any:
        return self._send(path, None, "DELETE")

    def wait_model(self, model_id: str, timeout: float = 120.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            model = self.get(f"/api/models/{model_id}")
            if model["status"] in ("done", "failed"):
                return model
            time.sleep(0.5)
        raise TimeoutError(f"model {model_id} not finished after {timeout} s")


def _wait_until_up(proc: subprocess.Popen[bytes], url: str, log: Path) -> None:
    deadline = time.monotonic() + STARTUP_SECONDS
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"`miss serve` exited with {proc.returncode}:\n{log.read_text()[-4000:]}")
        try:
            with urllib.request.urlopen(url + "/api/health", timeout=2) as response:
                if response.status == 200:
                    return
        except (urllib.error.URLError, ConnectionError, TimeoutError):
            pass
        time.sleep(0.3)
    pytest.fail(
        f"`miss serve` did not answer within {STARTUP_SECONDS} s:\n{log.read_text()[-4000:]}"
    )


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """``miss serve`` on a free 127.0.0.1 port with an empty temporary data folder."""
    with serve(tmp_path_factory) as running:
        yield running


@contextlib.contextmanager
def serve(tmp_path_factory: pytest.TempPathFactory, **settings: str) -> Iterator[Server]:
    """A ``miss serve`` of its own, logged in, with ``settings`` (``MISS_...`` variables)
    in its environment: for tests that need other settings than the session's server."""
    data_dir = tmp_path_factory.mktemp("miss-data")
    log = data_dir.parent / f"{data_dir.name}-serve.log"
    port = _free_port()
    env = {**os.environ, "MISS_DATA_DIR": str(data_dir), "MISS_ADMIN_PASSWORD": ADMIN_PASSWORD}
    env |= settings
    cmd = [sys.executable, "-m", "miss.cli", "serve", "--host", "127.0.0.1", "--port", str(port)]
    cmd += ["--data-dir", str(data_dir)]
    with log.open("wb") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=REPO)
    url = f"http://127.0.0.1:{port}"
    try:
        _wait_until_up(proc, url, log)
        running = Server(url, data_dir, log)
        running.log_in()
        yield running
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


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
def admin_password() -> str:
    return ADMIN_PASSWORD


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


@pytest.fixture(scope="session")
def phantom(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The synthetic CT head as NIfTI, written by the CLI as a user would."""
    path = tmp_path_factory.mktemp("upload") / "phantom-head.nii.gz"
    subprocess.run(
        [sys.executable, "-m", "miss.cli", "demo", str(path)], check=True, capture_output=True
    )
    return path
