"""Jobs survive the server: a real ``miss serve`` stopped (SIGTERM) or killed (SIGKILL)
mid-job and started again on the same data folder finishes every job."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest
from support import free_port
from support.realserver import Server, alive, serving

from miss.server.core.settings import Settings
from miss.server.jobs.state import JobState
from miss.server.main import serve
from miss.server.storage.db import FAILED, QUEUED, RUNNING, ModelRow, VolumeRow
from miss.server.storage.store import Store

JOBS = [{"level": level, "sample_rate": 4, "decimate": "none"} for level in (200, 260, 320)]


def submit_all(server: Server) -> list[str]:
    demo = server.http.get("/api/volumes").json()[0]["id"]
    ids = []
    for params in JOBS:
        r = server.http.post("/api/models", json={"volume": demo, **params})
        assert r.status_code == 202, r.text
        ids.append(r.json()["id"])
    return ids


def test_sigterm_requeues_and_restart_finishes(data_dir: Path, tmp_path: Path) -> None:
    data = data_dir
    server = Server(data, tmp_path / "server.log")
    ids = submit_all(server)
    server.wait(ids[0], ("running",))
    # uvicorn shuts down gracefully, then re-raises the signal it caught.
    assert server.stop(signal.SIGTERM) in (0, -signal.SIGTERM)
    assert "Application shutdown complete" in server.log.read_text()
    store = Store(data, Settings(data_dir=data).database_url)
    rows = [store.get_model(i) for i in ids]
    store.close()
    assert RUNNING not in [r.status for r in rows]  # the running job was put back, not lost
    assert all(r.attempts == 0 for r in rows if r.status == QUEUED)  # a clean stop costs no attempt
    with serving(data, tmp_path / "server.log", workers=2) as again:
        for model_id in ids:
            assert again.wait(model_id, ("done", "failed"))["status"] == "done"


def test_sigkill_mid_job_reruns_after_restart(data_dir: Path, tmp_path: Path) -> None:
    data = data_dir
    server = Server(data, tmp_path / "server.log")
    # Heavier than the others (decimation at sample rate 2), so it is surely mid-run.
    demo = server.http.get("/api/volumes").json()[0]["id"]
    r = server.http.post("/api/models", json={"volume": demo, "level": 300, "sample_rate": 2})
    model_id = r.json()["id"]
    server.wait(model_id, ("running",))
    store = Store(data, Settings(data_dir=data).database_url)
    deadline = time.monotonic() + 30
    while (pid := store.get_model(model_id).pid) is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert pid is not None
    server.stop(signal.SIGKILL)
    # The worker dies with the server (no orphan finishing a job that will run again).
    deadline = time.monotonic() + 10
    while alive(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not alive(pid), f"worker {pid} outlived the server:\n{server.log.read_text()}"
    left = store.get_model(model_id)
    assert left.status == RUNNING, left.__dict__  # as the killed server left it
    store.close()
    with serving(data, tmp_path / "server.log") as again:
        body = again.wait(model_id, ("done", "failed"))
        assert body["status"] == "done" and body["attempts"] == 2, body


def test_interrupted_twice_fails_with_reason(tmp_path: Path) -> None:
    store = Store(tmp_path, Settings(data_dir=tmp_path).database_url)
    store.init()
    with store.session.begin() as s:
        s.add(VolumeRow(id="v", name="v", slug="v", info={}))
        s.flush()  # the volume before its models (no ORM relationship orders them)
        s.add(
            ModelRow(
                id="once", volume_id="v", key="a", status=RUNNING, attempts=1, stage="decimate"
            )
        )
        s.add(
            ModelRow(
                id="twice", volume_id="v", key="b", status=RUNNING, attempts=2, stage="decimate"
            )
        )
    requeued, failed = JobState(store).recover(max_attempts=2)
    assert (requeued, failed) == (["once"], ["twice"])
    assert store.get_model("once").status == QUEUED
    twice = store.get_model("twice")
    assert twice.status == FAILED and twice.error.startswith("interrupted twice")
    store.close()


def test_a_supervisor_fails_only_the_run_it_started(tmp_path: Path) -> None:
    """A worker's exit seen after its job finished and was claimed again (another pid)
    must not fail the new run nor remove its files: CI once lost a model this way."""
    store = Store(tmp_path, Settings(data_dir=tmp_path).database_url)
    store.init()
    with store.session.begin() as s:
        s.add(VolumeRow(id="v", name="v", slug="v", info={}))
        s.flush()
        s.add(ModelRow(id="m", volume_id="v", key="a", status=RUNNING, pid=4242))
    state = JobState(store)
    assert not state.fail("m", "worker ended without recording a result", pid=1111)
    assert store.get_model("m").status == RUNNING
    assert state.fail("m", "worker ended without recording a result", pid=4242)
    assert store.get_model("m").status == FAILED
    store.close()


def test_second_server_on_same_data_dir_refuses(
    data_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    holder = Store(data_dir, Settings(data_dir=data_dir).database_url)
    holder.lock()  # as a running server holds it
    try:
        assert serve(port=free_port(), data_dir=str(data_dir)) == 1
    finally:
        holder.close()
    assert "another MISS server is using" in capsys.readouterr().err
