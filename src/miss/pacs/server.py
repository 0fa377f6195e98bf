"""Which PACS MISS talks to: :class:`PacsServer`, from the environment.

``MISS_PACS_URL`` is the DICOMweb root of the first (``http://127.0.0.1:8042/dicom-web``),
``MISS_PACS_NAME`` its name (``PACS``), ``MISS_PACS_AUTH_FILE`` a file holding its
credentials, ``MISS_PACS_TIMEOUT`` seconds per request (30). More servers:
``MISS_PACS2_URL``, ``MISS_PACS2_NAME`` ... up to ``MISS_PACS9_*``.

The credentials file holds one line: ``user:password`` (HTTP basic) or ``Bearer TOKEN``.
It is read when a request is made, never logged, never put on a command line, so it can
be rotated without a restart and kept readable by the server's account only.
"""

from __future__ import annotations

import os
import re
import stat
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

from miss.errors import BadParameter

DEFAULT_NAME = "PACS"
DEFAULT_TIMEOUT = 30.0
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9 ._-]{0,63}")  # whole: fullmatch


@dataclass(frozen=True)
class PacsServer:
    """One DICOMweb server: its name in MISS, its root URL, where its credentials are."""

    name: str
    url: str
    auth_file: Path | None = field(default=None, repr=False)
    timeout: float = DEFAULT_TIMEOUT

    def __post_init__(self) -> None:
        parts = urlsplit(self.url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise BadParameter(
                f"PACS URL {self.url!r} is not an http(s) URL; give the DICOMweb root, e.g. "
                "http://127.0.0.1:8042/dicom-web."
            )
        if parts.username or parts.password:
            raise BadParameter(
                "the PACS URL carries credentials; put them in the file MISS_PACS_AUTH_FILE "
                "names (user:password or Bearer TOKEN), never in the URL."
            )
        if not _NAME.fullmatch(self.name):
            raise BadParameter(
                f"PACS name {self.name!r} is not valid; use 1-64 letters, digits, spaces, "
                "'.', '_' or '-'."
            )
        if not self.timeout > 0:
            raise BadParameter(f"MISS_PACS_TIMEOUT must be positive, got {self.timeout}.")
        object.__setattr__(self, "url", self.url.rstrip("/"))

    @property
    def where(self) -> str:
        """How messages name it: ``PACS 'Orthanc' at http://127.0.0.1:8042/dicom-web``."""
        return f"PACS {self.name!r} at {self.url}"

    def credentials(self) -> tuple[str, str] | str | None:
        """(user, password) for basic auth, a bearer token, or None (no file set)."""
        if self.auth_file is None:
            return None
        try:
            info = self.auth_file.stat()
            text = self.auth_file.read_text(encoding="utf-8")
        except OSError as exc:
            raise BadParameter(
                f"cannot read the credentials file of {self.where} ({exc.strerror}); check "
                "MISS_PACS_AUTH_FILE and that the server's account may read it."
            ) from None
        if not stat.S_ISREG(info.st_mode):
            raise BadParameter(f"MISS_PACS_AUTH_FILE of {self.where} is not a regular file.")
        line = next((x.strip() for x in text.splitlines() if x.strip()), "")
        if line.lower().startswith("bearer "):
            return line[7:].strip()
        user, sep, password = line.partition(":")
        if not sep or not user:
            raise BadParameter(
                f"the credentials file of {self.where} must hold one line, user:password or "
                "Bearer TOKEN."
            )
        return (user, password)


def configured_servers(env: Mapping[str, str] | None = None) -> tuple[PacsServer, ...]:
    """The PACS named by ``MISS_PACS_URL`` (and ``MISS_PACS2_URL`` ... ``MISS_PACS9_URL``)."""
    env = os.environ if env is None else env
    servers: list[PacsServer] = []
    for n in ("", *map(str, range(2, 10))):
        prefix = f"MISS_PACS{n}_"
        url = env.get(prefix + "URL", "").strip()
        if not url:
            continue
        auth = env.get(prefix + "AUTH_FILE", "").strip()
        try:
            timeout = float(env.get(prefix + "TIMEOUT", "").strip() or DEFAULT_TIMEOUT)
        except ValueError:
            raise BadParameter(f"{prefix}TIMEOUT must be a number of seconds.") from None
        name = env.get(prefix + "NAME", "").strip() or (DEFAULT_NAME + n)
        servers.append(PacsServer(name, url, Path(auth) if auth else None, timeout))
    names = [s.name for s in servers]
    if len(set(names)) != len(names):
        raise BadParameter(f"two PACS have the same name ({names}); give each its own.")
    return tuple(servers)
