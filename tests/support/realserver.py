"""A real ``miss serve`` in a subprocess, for the tests that kill, restart or starve it.

Not a fixture module: ``Server`` is started and stopped by each test, because those tests
are about what happens between a start and the next one.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
from pg import database_url

ADMIN_PASSWORD = "admin-password-for-restarts"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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

    ``env`` adds to the environment (``MISS_*`` settings); ``wrap`` is a command prefix
    that ends by running its arguments (e.g. ``unshare -m sh -c '... exec "$@"' sh``);
    ``args`` are more options of ``miss serve``.
    """

    def __init__(
        self,
        data_dir: Path,
        log: Path,
        workers: int = 1,
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
        environ = {
            **os.environ,
            "MISS_WORKERS": str(workers),
            "MISS_ADMIN_PASSWORD": ADMIN_PASSWORD,
            "MISS_MAX_JOBS_PER_USER": "100",  # these tests queue several jobs at once
            **(env or {}),
        }
        if "MISS_DATABASE_URL" not in environ and (url := database_url(data_dir)):
            environ["MISS_DATABASE_URL"] = url  # MISS_TEST_DATABASE=postgres: tests/pg.py
        with open(log, "ab") as out:
            self.proc = subprocess.Popen(
                cmd, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=environ
            )
        self.http = httpx.Client(base_url=self.url, timeout=120)  # a busy machine
        self._wait_ready()
        self._log_in()

    def _log_in(self) -> None:
        r = self.http.post(
            "/api/auth/login", json={"username": "admin", "password": ADMIN_PASSWORD}
        )
        assert r.status_code == 200, r.text
        self.http.cookies.clear()
        self.token = r.json()["token"]
        self.http.headers["Authorization"] = f"Bearer {self.token}"

    def _wait_ready(self, timeout: float = 60) -> None:
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

    def wait(self, model_id: str, until: tuple[str, ...], timeout: float = 120) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            body = self.model(model_id)
            if body["status"] in until:
                return body
            time.sleep(0.1)
        raise AssertionError(
            f"{model_id} not {until} after {timeout} s: {body}\n{self.log.read_text()}"
        )

    def submit(self, volume: str, **params: Any) -> str:
        r = self.http.post("/api/models", json={"volume": volume, **params})
        assert r.status_code in (200, 202), r.text
        return r.json()["id"]

    def stop(self, sig: int) -> int:
        self.http.close()
        self.proc.send_signal(sig)
        return self.proc.wait(timeout=30)


@contextmanager
def serving(data_dir: Path, log: Path, workers: int = 1, **kwargs: Any) -> Iterator[Server]:
    server = Server(data_dir, log, workers, **kwargs)
    try:
        yield server
    finally:
        if server.proc.poll() is None:
            server.stop(signal.SIGTERM)
