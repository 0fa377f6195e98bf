"""A real ``miss serve`` in a subprocess: the one starter of the server, browser, PACS and
attack tests that need a process (to kill, restart or starve it, or to load its pages).

Not a fixture module: ``Server`` is started and stopped by each test (or by the browser
tests' session fixture), because those tests are about what a real process does.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx

from support import ADMIN_PASSWORD, REPO, free_port
from support.models import JOB_TIMEOUT, wait_for_model
from support.pg import database_url

STARTUP_SECONDS = 90  # a cold start on a busy 2-core machine
#: With a worker count set, the tests queue several jobs at once.
QUEUE_SEVERAL = {"MISS_MAX_JOBS_PER_USER": "100"}


def alive(pid: int) -> bool:
    """True while ``pid`` runs (a zombie waiting for its reaper counts as dead)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, IndexError):
        return False
    return state not in ("Z", "X")


def wait_dead(pid: int, timeout: float = 10) -> bool:
    deadline = time.monotonic() + timeout
    while alive(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    return not alive(pid)


class Server:
    """``miss serve`` in a subprocess on a free loopback port, logged in as admin.

    ``workers`` sets ``MISS_WORKERS`` (None: the server's own default and limits);
    ``env`` adds to the environment (``MISS_*`` settings); ``wrap`` is a command prefix
    that ends by running its arguments (e.g. ``unshare -m sh -c '... exec "$@"' sh``);
    ``args`` are more options of ``miss serve``. ``http`` is an httpx client carrying
    the admin's token; ``get``/``post``/``delete`` are urllib JSON calls that raise
    ``urllib.error.HTTPError`` on a 4xx or 5xx, as a script's would.
    """

    def __init__(
        self,
        data_dir: Path,
        log: Path,
        workers: int | None = 1,
        env: dict[str, str] | None = None,
        wrap: Sequence[str] = (),
        args: Sequence[str] = (),
    ) -> None:
        self.data_dir, self.log = data_dir, log
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        cmd = [
            *wrap,
            sys.executable,
            "-m",
            "miss.cli",
            "serve",
            "--port",
            str(self.port),
            "--data-dir",
            str(data_dir),
            *args,
        ]
        environ = {**os.environ, "MISS_ADMIN_PASSWORD": ADMIN_PASSWORD}
        if workers is not None:
            environ |= {"MISS_WORKERS": str(workers), **QUEUE_SEVERAL}
        environ |= env or {}
        if "MISS_DATABASE_URL" not in environ and (url := database_url(data_dir)):
            environ["MISS_DATABASE_URL"] = url  # MISS_TEST_DATABASE=postgres: support/pg.py
        with open(log, "ab") as out:
            self.proc = subprocess.Popen(
                cmd, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                env=environ, cwd=REPO,
            )  # fmt: skip
        self.http = httpx.Client(base_url=self.url, timeout=120)  # a busy machine
        self._wait_ready()
        self.log_in()

    def log_in(self, name: str = "admin", password: str = ADMIN_PASSWORD) -> str:
        """Log ``http`` (and the JSON calls) in with a bearer token; returns the token."""
        r = self.http.post("/api/auth/login", json={"username": name, "password": password})
        assert r.status_code == 200, r.text
        self.http.cookies.clear()
        self.token = r.json()["token"]
        self.http.headers["Authorization"] = f"Bearer {self.token}"
        return self.token

    def _wait_ready(self, timeout: float = STARTUP_SECONDS) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            assert self.proc.poll() is None, f"server exited early:\n{self.log.read_text()}"
            try:
                if self.http.get("/api/health").status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        raise AssertionError(f"server not ready after {timeout} s:\n{self.log.read_text()}")

    def path(self, inside: Path) -> Path:
        """``inside`` (a path in the server's data folder) as this process sees it: through
        ``/proc/<pid>/root`` when the server runs in a mount namespace of its own."""
        return Path(f"/proc/{self.proc.pid}/root") / inside.relative_to("/")

    def model(self, model_id: str) -> dict[str, Any]:
        return self.http.get(f"/api/models/{model_id}").json()

    def wait(
        self, model_id: str, until: tuple[str, ...], timeout: float = JOB_TIMEOUT
    ) -> dict[str, Any]:
        try:
            return wait_for_model(self.http.get, model_id, until, timeout, poll=0.1)
        except AssertionError as e:
            raise AssertionError(f"{e}\n{self.log.read_text()}") from None

    def wait_model(self, model_id: str, timeout: float = JOB_TIMEOUT) -> dict[str, Any]:
        """The model once done or failed (the browser tests' spelling)."""
        return wait_for_model(self.get, model_id, timeout=timeout, poll=0.5)

    def _send(self, path: str, body: dict[str, Any] | None, method: str) -> Any:
        headers = {"Content-Type": "application/json", "Authorization": f"Bearer {self.token}"}
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

    def submit(self, volume: str, **params: Any) -> str:
        r = self.http.post("/api/models", json={"volume": volume, **params})
        assert r.status_code in (200, 202), r.text
        return r.json()["id"]

    def stop(self, sig: int) -> int:
        self.http.close()
        self.proc.send_signal(sig)
        return self.proc.wait(timeout=30)


@contextmanager
def serving(data_dir: Path, log: Path, workers: int | None = 1, **kwargs: Any) -> Iterator[Server]:
    """A started :class:`Server`, stopped (SIGTERM, then SIGKILL) when the block ends."""
    server = Server(data_dir, log, workers, **kwargs)
    try:
        yield server
    finally:
        if server.proc.poll() is None:
            try:
                server.stop(signal.SIGTERM)
            except subprocess.TimeoutExpired:
                server.proc.kill()
                server.proc.wait()
