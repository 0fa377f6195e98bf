"""Managing one's models: cancel a queued or running job (its worker killed, nothing it
wrote left, its slot free again), rename a model, and the words a colleague reads at a
model that is not theirs."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from support.realserver import alive, serving

from miss.server.core.settings import Settings
from miss.server.storage.store import Store

NOBODY = {"Authorization": ""}


def add_user(client: TestClient, name: str) -> dict[str, str]:
    """A new ordinary account: its request headers (bearer token)."""
    r = client.post("/api/users", json={"name": name, "password": f"{name}-password"})
    assert r.status_code == 201, r.text
    body = {"username": name, "password": f"{name}-password"}
    r = client.post("/api/auth/login", json=body, headers=NOBODY)
    assert r.status_code == 200, r.text
    client.cookies.clear()  # the client stays the administrator's
    return {"Authorization": f"Bearer {r.json()['token']}"}


def worker_pid(data: Path, model_id: str) -> int:
    """The pid of the worker running ``model_id``, read from its row once it names it."""
    store = Store(data, Settings(data_dir=data).database_url)
    try:
        deadline = time.monotonic() + 60
        while (pid := store.get_model(model_id).pid) is None and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        store.close()
    assert pid is not None, f"no worker for {model_id}"
    return pid


@pytest.mark.slow  # kills a real worker process
def test_cancel_kills_the_worker_removes_its_files_and_frees_the_slot(
    data_dir: Path, tmp_path: Path
) -> None:
    # One job at a time per account, so the slot it held is seen to be free again.
    env = {"MISS_MAX_JOBS_PER_USER": "1"}
    with serving(data_dir, tmp_path / "server.log", env=env) as server:
        demo = server.http.get("/api/volumes").json()[0]["id"]
        model_id = server.submit(demo, level=300, sample_rate=1)  # seconds of work
        server.wait(model_id, ("running",))
        folder = data_dir / "models" / model_id
        pid = worker_pid(data_dir, model_id)
        r = server.http.post(f"/api/models/{model_id}/cancel")
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["status"] == "failed" and "cancelled by admin" in body["error"], body
        assert not alive(pid), pid  # killed and waited for before the answer
        left = sorted(p.name for p in folder.glob("*") if p.name.startswith(("model.", "preview")))
        assert left == [], left
        assert not (folder / "lod").exists()
        # The account's slot is free: another job is queued, not refused.
        other = server.http.post("/api/models", json={"volume": demo, "level": 200})
        assert other.status_code == 202, other.text
        # A job that has ended cannot be cancelled; the answer says what to do instead.
        again = server.http.post(f"/api/models/{model_id}/cancel")
        assert again.status_code == 409 and "delete the model" in again.json()["detail"]
        # Cancelled too, the other frees the slot; the first, submitted again, is queued anew.
        assert server.http.post(f"/api/models/{other.json()['id']}/cancel").status_code == 200
        assert server.submit(demo, level=300, sample_rate=1) == model_id


def test_rename_a_model(client: TestClient, demo_id: str) -> None:
    r = client.post("/api/models", json={"volume": demo_id, "level": 310, "sample_rate": 4})
    model_id = r.json()["id"]
    assert r.json()["name"] is None
    r = client.patch(f"/api/models/{model_id}", json={"name": "  Skull  for\nsurgery "})
    assert r.status_code == 200, r.text
    assert r.json()["name"] == "Skull for surgery"
    listed = client.get("/api/models", params={"volume": demo_id}).json()
    assert [m["name"] for m in listed if m["id"] == model_id] == ["Skull for surgery"]
    assert client.patch(f"/api/models/{model_id}", json={"name": " "}).json()["name"] is None
    too_long = client.patch(f"/api/models/{model_id}", json={"name": "x" * 201})
    assert too_long.status_code == 422


def test_a_colleague_reads_that_the_model_is_not_shared_with_them(
    client: TestClient, demo_id: str
) -> None:
    r = client.post("/api/models", json={"volume": demo_id, "level": 320, "sample_rate": 4})
    model_id = r.json()["id"]
    colleague = add_user(client, "colleague")
    r = client.get(f"/api/models/{model_id}", headers=colleague)
    assert r.status_code == 404  # the same status as for no model at all
    detail = r.json()["detail"]
    assert "not shared with you" in detail and "share link" in detail, detail
    # Somebody not signed in learns nothing of it.
    r = client.get(f"/api/models/{model_id}", headers=NOBODY)
    assert r.status_code == 401 and model_id not in r.text
