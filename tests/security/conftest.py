"""Fixtures for the attack tests: the server tests' fixtures (seeded data folder, apps,
upload files) and ``realserver`` (a real ``miss serve`` on a free loopback port)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

_SERVER_TESTS = Path(__file__).resolve().parents[1] / "server"
sys.path.insert(0, str(_SERVER_TESTS))  # ``from realserver import serving`` as in tests/server

_spec = importlib.util.spec_from_file_location("server_fixtures", _SERVER_TESTS / "conftest.py")
assert _spec is not None and _spec.loader is not None
_fixtures = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_fixtures)
sys.modules.setdefault("server_fixtures", _fixtures)  # its helpers: running_row ...
globals().update({k: v for k, v in vars(_fixtures).items() if not k.startswith("_")})
