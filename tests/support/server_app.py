"""Fixtures for the server, PACS and attack tests: a seeded data folder, apps on copies of it
(logged in as the administrator), upload files. A plugin of every run (``tests/conftest.py``)."""

from __future__ import annotations

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
from miss.server.core.settings import Settings
from miss.server.storage.db import RUNNING, ModelRow
from miss.server.storage.store import Store, new_id
from miss.server.volumes.ingest import register_demo
from miss.spec import JobSpec
from support import ADMIN_PASSWORD
from support.models import JOB_TIMEOUT, wait_for_model
from support.pg import copy_seed, database_url, settings_for


def log_in(client: TestClient, name: str = "admin", password: str = ADMIN_PASSWORD) -> str:
    """Log ``client`` in with a bearer token (as scripts do: no cookie, so no CSRF)."""
    r = client.post("/api/auth/login", json={"username": name, "password": password})
    assert r.status_code == 200, r.text
    client.cookies.clear()
    token = r.json()["token"]
    client.headers["Authorization"] = f"Bearer {token}"
    return token


def started(data: Path, password: str = ADMIN_PASSWORD) -> TestClient:
    """A server's app started on the data folder ``data`` (its administrator's
    ``password``) and logged in as the administrator; the caller closes it (``__exit__``)."""
    client = TestClient(create_app(settings_for(data, admin_password=password)))
    client.__enter__()
    log_in(client, password=password)
    return client


@pytest.fixture(scope="session")
def admin_password() -> str:
    return ADMIN_PASSWORD


@pytest.fixture
def login() -> Callable[..., TestClient]:
    """``login(client)`` logs a started TestClient in as admin and returns it."""

    def start(
        client: TestClient, name: str = "admin", password: str = ADMIN_PASSWORD
    ) -> TestClient:
        log_in(client, name, password)
        return client

    return start


@pytest.fixture(scope="session")
def seeded_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A data folder with the demo phantom registered, made once: the phantom takes seconds
    to compute, so every app below starts from a copy of this folder."""
    path = tmp_path_factory.mktemp("seed") / "data"
    store = Store(path, Settings(data_dir=path, database_url=database_url(path)).database_url)
    store.init()
    register_demo(store)
    store.close()
    return path


@pytest.fixture
def data_dir(seeded_dir: Path, tmp_path: Path) -> Path:
    return copy_seed(seeded_dir, tmp_path / "data")


@pytest.fixture(scope="module")
def client(seeded_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    """One app per test module on its own copy of the seeded folder (default limits)."""
    data = copy_seed(seeded_dir, tmp_path_factory.mktemp("api") / "data")
    with TestClient(create_app(settings_for(data, admin_password=ADMIN_PASSWORD))) as c:
        log_in(c)
        yield c


@pytest.fixture
def make_client(tmp_path: Path) -> Iterator[Callable[..., TestClient]]:
    """Start an app with custom settings (no demo unless asked) on a fresh folder, logged in
    as the administrator."""
    clients: list[TestClient] = []

    def start(**overrides: Any) -> TestClient:
        values = {"data_dir": tmp_path / f"data{len(clients)}", "demo": False}
        values |= {"admin_password": ADMIN_PASSWORD} | overrides
        c = TestClient(create_app(settings_for(**values)))
        c.__enter__()
        clients.append(c)
        log_in(c)
        return c

    yield start
    for c in clients:
        c.__exit__(None, None, None)


@pytest.fixture
def demo_id(client: TestClient) -> str:
    volumes = client.get("/api/volumes").json()
    return next(v["id"] for v in volumes if v["name"] == "Demo head phantom (synthetic CT)")


def running_row(store: Store, volume_id: str) -> str:
    """A model row a test drives by hand: running, never claimed by an app's queue."""
    model_id = new_id()
    with store.session.begin() as s:
        s.add(ModelRow(id=model_id, volume_id=volume_id, key=model_id, status=RUNNING,
                       spec=JobSpec.of(level=300).to_dict(), stage="surface"))  # fmt: skip
    return model_id


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


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


@pytest.fixture(scope="module")
def people(client: TestClient) -> dict[str, dict[str, str]]:
    """Two ordinary users of the module's app, alice and bob: name -> request headers."""
    out = {}
    for name in ("alice", "bob"):
        r = client.post("/api/users", json={"name": name, "password": f"{name}-password"})
        assert r.status_code == 201, r.text
        login = client.post(
            "/api/auth/login",
            json={"username": name, "password": f"{name}-password"},
            headers={"Authorization": ""},
        )
        client.cookies.clear()  # this client stays the admin's, by bearer token
        out[name] = bearer(login.json()["token"])
    return out


@pytest.fixture(scope="session")
def small_nifti(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """A 24^3 CT-like ball (HU) as .nii.gz: an upload that reads and meshes in no time."""
    import nibabel as nib
    import numpy as np

    i, j, k = np.mgrid[:24, :24, :24]
    ball = np.where((i - 12) ** 2 + (j - 12) ** 2 + (k - 12) ** 2 < 64, 1000, -1000)
    path = tmp_path_factory.mktemp("nifti") / "ball.nii.gz"
    nib.save(nib.Nifti1Image(ball.astype(np.int16), np.diag([1.5, 1.5, 2.0, 1.0])), path)
    return path.read_bytes()


def upload_as(
    client: TestClient, headers: dict[str, str], content: bytes, name: str = "ball.nii.gz"
) -> dict[str, Any]:
    r = client.post("/api/volumes", files={"file": (name, content)}, headers=headers)
    assert r.status_code == 201, r.text
    return r.json()


@pytest.fixture(scope="session")
def upload_for() -> Callable[..., dict[str, Any]]:
    """``upload_for(client, headers, content)``: the new volume's JSON."""
    return upload_as


def make_model(
    client: TestClient, headers: dict[str, str], volume_id: str, level: float = 0.0
) -> dict[str, Any]:
    """A finished model (sample rate 1, no decimation) of a volume."""
    body = {"volume": volume_id, "level": level, "decimate": "none"}
    r = client.post("/api/models", json=body, headers=headers)
    assert r.status_code in (200, 202), r.text
    deadline = time.monotonic() + JOB_TIMEOUT
    while (model := client.get(f"/api/models/{r.json()['id']}", headers=headers).json())[
        "status"
    ] not in ("done", "failed"):
        assert time.monotonic() < deadline, model
        time.sleep(0.1)
    assert model["status"] == "done", model
    return model


@pytest.fixture(scope="session")
def model_for() -> Callable[..., dict[str, Any]]:
    """``model_for(client, headers, volume_id, level=0)``: a finished model's JSON."""
    return make_model
