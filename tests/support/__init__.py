"""What the test folders share: the repository and datasets paths, a free port, the
administrator's password.

``tests/conftest.py`` registers the fixture modules here with ``pytest_plugins``; pytest puts
``tests/`` on ``sys.path`` (the rootdir conftest, prepend import mode), so test files import
``from support import ...`` and ``from support.realserver import Server``.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
#: The real CT/MR scans: ``$MISS_DATASETS``, else ``../shared/datasets`` beside the repository.
DATASETS = Path(os.environ.get("MISS_DATASETS", REPO.parent / "shared" / "datasets"))
#: The administrator's password on every server the tests start (apps and processes).
ADMIN_PASSWORD = "admin-password-for-tests"


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on at the time of asking."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
