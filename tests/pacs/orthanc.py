"""A real Orthanc (Debian's ``orthanc`` + ``orthanc-dicomweb``) on free loopback ports.

Started in a temporary folder with its own configuration: HTTP on 127.0.0.1 only, DICOM
port off, a user and password, the DICOMweb plugin alone. ``make test`` installs the
packages (its ``orthanc`` target), as it does chromium.
"""

from __future__ import annotations

import json
import os
import secrets
import signal
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import requests
from support import free_port

ORTHANC = Path("/usr/sbin/Orthanc")
DICOMWEB_PLUGIN = Path("/usr/share/orthanc/plugins/libOrthancDicomWeb.so")


@dataclass
class Orthanc:
    """A running Orthanc: its REST root, its DICOMweb root, the login, its process."""

    url: str
    user: str
    password: str
    auth_file: Path
    proc: subprocess.Popen[bytes]
    folder: Path

    @property
    def dicomweb(self) -> str:
        return f"{self.url}/dicom-web"

    def rest(self, method: str, path: str, **kwargs: object) -> requests.Response:
        """Orthanc's own REST API (for checks the DICOMweb API does not make)."""
        response = requests.request(
            method, self.url + path, auth=(self.user, self.password), timeout=60, **kwargs
        )  # type: ignore[arg-type]
        response.raise_for_status()
        return response

    def env(self, name: str = "Orthanc") -> dict[str, str]:
        """The settings that point MISS at it."""
        return {
            "MISS_PACS_URL": self.dicomweb,
            "MISS_PACS_NAME": name,
            "MISS_PACS_AUTH_FILE": str(self.auth_file),
        }

    @contextmanager
    def paused(self) -> Iterator[None]:
        """Orthanc stopped (SIGSTOP): connections are accepted by the kernel, never
        answered, as a PACS that hangs."""
        os.kill(self.proc.pid, signal.SIGSTOP)
        try:
            yield
        finally:
            os.kill(self.proc.pid, signal.SIGCONT)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)


def available() -> str | None:
    """Why Orthanc cannot run here, or None."""
    if not ORTHANC.is_file():
        return f"{ORTHANC} not installed (make test installs Debian's orthanc)"
    if not DICOMWEB_PLUGIN.is_file():
        return f"{DICOMWEB_PLUGIN} not installed (Debian's orthanc-dicomweb)"
    return None


def start(folder: Path, lua: str = "") -> Orthanc:
    """Start Orthanc in ``folder`` on a free loopback port; waits until it answers.
    ``lua``: a Lua script Orthanc runs (e.g. a ``ReceivedInstanceFilter`` that refuses)."""
    folder.mkdir(parents=True, exist_ok=True)
    port = free_port()
    user, password = "miss", secrets.token_urlsafe(12)
    config = {
        "Name": "MISS-test",
        "StorageDirectory": str(folder / "db"),
        "IndexDirectory": str(folder / "db"),
        "HttpPort": port,
        "HttpBindAddress": "127.0.0.1",  # not in 1.10; RemoteAccessAllowed below holds
        "RemoteAccessAllowed": False,
        "AuthenticationEnabled": True,
        "RegisteredUsers": {user: password},
        "DicomServerEnabled": False,
        "DicomPort": free_port(),
        "OrthancExplorerEnabled": False,
        "WebDavEnabled": False,
        "HttpDescribeErrors": True,
        "StableAge": 1,
        "Plugins": [str(DICOMWEB_PLUGIN)],
        "DicomWeb": {"Enable": True, "Root": "/dicom-web/", "EnableWado": False},
    }
    if lua:
        (folder / "filter.lua").write_text(lua)
        config["LuaScripts"] = [str(folder / "filter.lua")]
    (folder / "orthanc.json").write_text(json.dumps(config, indent=1))
    auth_file = folder / "pacs-auth"
    auth_file.write_text(f"{user}:{password}\n")
    auth_file.chmod(0o600)
    log = open(folder / "orthanc.log", "wb")  # noqa: SIM115 - kept open for the process
    proc = subprocess.Popen(
        [str(ORTHANC), str(folder / "orthanc.json")],
        stdout=log,
        stderr=subprocess.STDOUT,
        cwd=folder,
        start_new_session=True,
    )
    orthanc = Orthanc(f"http://127.0.0.1:{port}", user, password, auth_file, proc, folder)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"Orthanc exited: {(folder / 'orthanc.log').read_text()[-2000:]}")
        try:
            orthanc.rest("GET", "/system")
            return orthanc
        except requests.RequestException:
            time.sleep(0.2)
    orthanc.stop()
    raise RuntimeError("Orthanc did not answer within 60 s")
