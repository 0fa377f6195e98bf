"""Fixtures for the server tests: a seeded data folder, apps on copies of it, upload files."""

from __future__ import annotations

import shutil
import time
import warnings
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from starlette.exceptions import StarletteDeprecationWarning

with warnings.catch_warnings():
    # Starlette 1.x prefers httpx2 for its TestClient and warns (an error under our
    # pytest settings) when only httpx is installed; the client works the same.
    warnings.simplefilter("ignore", StarletteDeprecationWarning)
    from fastapi.testclient import TestClient

from miss.server.app import create_app
from miss.server.ingest import register_demo
from miss.server.settings import Settings
from miss.server.store import Store

JOB_TIMEOUT = 120.0


@pytest.fixture(scope="session")
def seeded_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A data folder with the demo phantom registered, made once: the phantom takes seconds
    to compute, so every app below starts from a copy of this folder."""
    path = tmp_path_factory.mktemp("seed") / "data"
    store = Store(path, Settings(data_dir=path).database_url)
    store.init()
    register_demo(store)
    store.close()
    return path


def copy_seed(seeded_dir: Path, dest: Path) -> Path:
    shutil.copytree(seeded_dir, dest)
    return dest


@pytest.fixture
def data_dir(seeded_dir: Path, tmp_path: Path) -> Path:
    return copy_seed(seeded_dir, tmp_path / "data")


@pytest.fixture(scope="module")
def client(seeded_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    """One app per test module on its own copy of the seeded folder (default limits)."""
    data = copy_seed(seeded_dir, tmp_path_factory.mktemp("api") / "data")
    with TestClient(create_app(Settings(data_dir=data))) as c:
        yield c


@pytest.fixture
def make_client(tmp_path: Path) -> Iterator[Callable[..., TestClient]]:
    """Start an app with custom settings (no demo unless asked) on a fresh folder."""
    clients: list[TestClient] = []

    def start(**overrides: Any) -> TestClient:
        values = {"data_dir": tmp_path / f"data{len(clients)}", "demo": False} | overrides
        c = TestClient(create_app(Settings(**values)))
        c.__enter__()
        clients.append(c)
        return c

    yield start
    for c in clients:
        c.__exit__(None, None, None)


@pytest.fixture
def demo_id(client: TestClient) -> str:
    volumes = client.get("/api/volumes").json()
    return next(v["id"] for v in volumes if v["name"] == "Demo head phantom (synthetic CT)")


def wait_for_model(
    client: TestClient, model_id: str, timeout: float = JOB_TIMEOUT
) -> dict[str, Any]:
    """Poll a model until done or failed; fail the test on timeout."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        body = client.get(f"/api/models/{model_id}").json()
        if body["status"] in ("done", "failed"):
            return body
        time.sleep(0.2)
    raise AssertionError(f"model {model_id} not finished after {timeout} s: {body}")


@pytest.fixture
def wait_done() -> Callable[..., dict[str, Any]]:
    return wait_for_model


@pytest.fixture(scope="session")
def dicom_zip(datasets: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The GE gantry-tilt head CT series, zipped inside a folder as people send it."""
    path = tmp_path_factory.mktemp("zips") / "ct_head_dicom_ge_gantrytilt.zip"
    folder = datasets / "ct_head_dicom_ge_gantrytilt"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for f in sorted(folder.iterdir()):
            zf.write(f, f"series/{f.name}")
    return path
