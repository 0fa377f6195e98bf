"""Fair use of the job workers (issue 39): one account's jobs never hold another's for
long, a job over its CPU or bytes-written limit fails with a message naming the limit
and leaves nothing behind, and an account over its disk quota is refused (507/413)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import closing
from datetime import timedelta
from pathlib import Path
from typing import Any

import httpx
import pytest
from support.pg import copy_seed, settings_for
from support.realserver import Server, serving

from miss.server.storage.db import QUEUED, ModelRow, utcnow
from miss.server.storage.store import Store, new_id
from miss.spec import JobSpec

DEMO = "Demo head phantom (synthetic CT)"


def _queue_rows(data: Path, jobs: list[tuple[str, float]], **params: Any) -> list[str]:
    """Queued rows on the demo volume, oldest first: (account, level) each, and
    ``params`` for all (a quick one at sample rate 2 by default); no server runs yet, so
    the queue's order alone decides which starts when."""
    params = params or {"sample_rate": 2, "decimate": "none"}
    settings = settings_for(data)
    store = Store(data, settings.database_url)
    try:
        volume = next(v for v in store.list_volumes() if v.name == DEMO)
        first, ids = utcnow(), []
        for n, (account, level) in enumerate(jobs):
            spec = JobSpec.of(level=level, **params)
            row = ModelRow(
                id=new_id(), volume_id=volume.id, key=spec.key(), spec=spec.to_dict(),
                status=QUEUED, submitted_by=account, created_at=first + timedelta(seconds=n),
            )  # fmt: skip
            with store.session.begin() as s:
                s.add(row)
            ids.append(row.id)
        return ids
    finally:
        store.close()


def test_round_robin_between_accounts(seeded_dir: Path, tmp_path: Path) -> None:
    """Alice queues three jobs, then Bob one: with one real worker, Bob's job starts
    right after Alice's first, not behind all three (the old queue: first in, first out)."""
    data = copy_seed(seeded_dir, tmp_path / "data")
    jobs = [("alice", 100.0), ("alice", 200.0), ("alice", 300.0), ("bob", 400.0)]
    ids = _queue_rows(data, jobs)
    with serving(data, tmp_path / "server.log", env={"MISS_DEMO": "0"}) as server:
        ended = [server.wait(i, ("done", "failed")) for i in ids]
    assert all(m["status"] == "done" for m in ended), ended
    order = [jobs[ids.index(m["id"])][0] for m in sorted(ended, key=lambda m: m["started"])]
    assert order == ["alice", "bob", "alice", "alice"], order


def test_a_worker_is_left_for_another_account(seeded_dir: Path, tmp_path: Path) -> None:
    """Alice's two long jobs came first and there are two workers: the second waits, so
    the administrator's job, posted while Alice's first runs, starts before it (the old
    queue gave Alice both workers, and the next account waited for one of her jobs)."""
    data = copy_seed(seeded_dir, tmp_path / "data")
    heavy = {"components": "split", "smooth": 500}
    alice = _queue_rows(data, [("alice", 300.0), ("alice", 310.0)], **heavy)
    with serving(data, tmp_path / "server.log", workers=2, env={"MISS_DEMO": "0"}) as server:
        first = server.wait(alice[0], ("running", "done", "failed"))
        assert first["status"] == "running", "alice's first job ended before the test looked"
        volume = next(v["id"] for v in server.http.get("/api/volumes").json())
        mine = server.submit(volume, level=500.0, sample_rate=2, decimate="none")
        ended = [server.wait(i, ("done", "failed"), timeout=300) for i in (*alice, mine)]
    assert all(m["status"] == "done" for m in ended), ended
    assert ended[2]["started"] < ended[1]["started"], ended


def _policies(pid: int) -> set[int]:
    """The scheduling policy of every thread of process ``pid`` (empty once it ended)."""
    found = set()
    for task in Path(f"/proc/{pid}/task").glob("*"):
        with contextlib.suppress(OSError):  # the thread ended meanwhile
            found.add(os.sched_getscheduler(int(task.name)))
    return found


def _computing(server: Server, model_id: str) -> int:
    """The worker pid of ``model_id`` once its job reports progress (so it has chosen
    its priority), from the database the server writes."""
    for _ in range(600):
        body = server.wait(model_id, ("running", "done", "failed"))
        assert body["status"] == "running", f"the job ended before the test looked: {body}"
        if body.get("stage") not in (None, "", "starting"):
            break
        time.sleep(0.1)
    store = Store(server.data_dir, settings_for(server.data_dir).database_url)
    try:
        pid = store.get_model(model_id).pid
    finally:
        store.close()
    assert pid, "the running job has no worker pid recorded"
    return pid


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="Linux scheduling policies")
def test_a_flooding_accounts_job_runs_behind_anothers(seeded_dir: Path, tmp_path: Path) -> None:
    """Alice has a long job running and another queued; the administrator posts one job.
    Every thread of Alice's worker runs at SCHED_IDLE, every thread of the
    administrator's at SCHED_BATCH, so on a contended core his job gets five times hers
    (the old workers all ran at SCHED_IDLE: the flood's threads took as much CPU as his).
    Once he posts a second job, his first goes behind as well."""
    data = copy_seed(seeded_dir, tmp_path / "data")
    alice = _queue_rows(data, [("alice", 300.0), ("alice", 310.0)], **HEAVY)
    with serving(data, tmp_path / "server.log", workers=2, env={"MISS_DEMO": "0"}) as server:
        hers = _computing(server, alice[0])
        levels = [level + 5 for level in HEAVY["levels"]]
        mine = _computing(server, server.submit(_demo(server), **{**HEAVY, "levels": levels}))
        assert _policies(hers) == {os.SCHED_IDLE}, _policies(hers)
        assert _policies(mine) == {os.SCHED_BATCH}, _policies(mine)
        # a second job of his, posted while the first runs: the first goes behind too
        server.submit(_demo(server), **{**HEAVY, "levels": [level + 7 for level in levels]})
        for _ in range(100):
            if _policies(mine) == {os.SCHED_IDLE}:
                break
            time.sleep(0.1)
        assert _policies(mine) == {os.SCHED_IDLE}, _policies(mine)


@pytest.fixture
def limited(seeded_dir: Path, tmp_path: Path) -> Iterator[Callable[..., Server]]:
    """``limited(MISS_...=value)``: a real server on a copy of the seeded folder (the demo
    phantom) with these settings, logged in as the administrator."""
    servers: list[Server] = []

    def start(**env: str) -> Server:
        data = copy_seed(seeded_dir, tmp_path / f"data{len(servers)}")
        servers.append(Server(data, tmp_path / "server.log", env={"MISS_DEMO": "0", **env}))
        return servers[-1]

    yield start
    for server in servers:
        if server.proc.poll() is None:
            server.stop(signal.SIGTERM)


def _demo(server: Server) -> str:
    return next(v["id"] for v in server.http.get("/api/volumes").json() if v["name"] == DEMO)


def _usage(server: Server) -> dict[str, dict[str, Any]]:
    r = server.http.get("/api/admin/usage")
    assert r.status_code == 200, r.text
    return {u["account"]: u for u in r.json()}


def _fails_clean(server: Server, body: dict[str, Any], setting: str) -> None:
    """The job of ``body`` fails naming ``setting``, and leaves no model file, no listed
    file, and the admin's disk use as before."""
    before = server.http.get("/api/admin/usage")  # looked at last: the job comes first
    model_id = server.submit(**body)
    model = server.wait(model_id, ("done", "failed"))
    assert model["status"] == "failed", model
    assert setting in model["error"] and "administrator" in model["error"], model["error"]
    assert not model["files"], model
    folder = server.data_dir / "models" / model_id
    left = sorted(p.name for p in folder.iterdir() if p.name != "worker.log")
    assert left == [], left
    assert before.status_code == 200, before.text
    admin = next(u for u in before.json() if u["account"] == "admin")
    assert _usage(server)["admin"]["bytes"] == admin["bytes"]


#: A job of many seconds of CPU on the demo phantom: 16 levels, smoothed, each piece apart.
HEAVY = {
    "levels": [float(level) for level in range(-400, 1200, 100)],
    "components": "split",
    "smooth": 500,
}


def test_job_over_its_cpu_limit_fails_and_leaves_nothing(
    limited: Callable[..., Server],
) -> None:
    server = limited(MISS_JOB_CPU_SECONDS="1")
    _fails_clean(server, {"volume": _demo(server), **HEAVY}, "MISS_JOB_CPU_SECONDS")


def test_job_over_its_bytes_limit_fails_and_leaves_nothing(
    limited: Callable[..., Server],
) -> None:
    server = limited(MISS_JOB_WRITE_MB="0.05")
    body = {"volume": _demo(server), "level": 300, "decimate": "none"}
    _fails_clean(server, body, "MISS_JOB_WRITE_MB")


def _user(server: Server, name: str) -> httpx.Client:
    """An ordinary account ``name`` made by the administrator, logged in by bearer token."""
    password = f"{name}-password-0"
    r = server.http.post("/api/users", json={"name": name, "password": password})
    assert r.status_code == 201, r.text
    return _logged_in(server, name)


def _logged_in(server: Server, name: str) -> httpx.Client:
    client = httpx.Client(base_url=server.url, timeout=120)
    r = client.post("/api/auth/login", json={"username": name, "password": f"{name}-password-0"})
    assert r.status_code == 200, r.text
    client.cookies.clear()
    client.headers["Authorization"] = f"Bearer {r.json()['token']}"
    return client


def test_admin_sees_usage_per_account_others_do_not(
    limited: Callable[..., Server], small_nifti: bytes
) -> None:
    server = limited()
    with closing(_user(server, "alice")) as alice:
        r = alice.post("/api/volumes", files={"file": ("ball.nii.gz", small_nifti)})
        assert r.status_code == 201, r.text
        refused = alice.get("/api/admin/usage")
        assert refused.status_code == 403, refused.text
    usage = _usage(server)
    assert usage["alice"]["volumes"] == 1 and usage["alice"]["bytes"] > len(small_nifti) // 2
    assert usage["alice"]["models"] == 0 and set(usage) >= {"admin", "alice"}
    env = {**os.environ, "MISS_DATABASE_URL": settings_for(server.data_dir).database_url}
    cmd = [sys.executable, "-m", "miss.cli", "user", "usage", "--data-dir", str(server.data_dir)]
    table = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True).stdout
    assert any(line.split()[:2] == ["alice", "1"] for line in table.splitlines()), table


def test_account_over_its_quota_gets_507_and_413(
    limited: Callable[..., Server], small_nifti: bytes
) -> None:
    """Alice fills her quota with one volume: her next upload and her next job get 507,
    an upload larger than the whole quota 413, and nothing of them is kept."""
    first = limited()
    with closing(_user(first, "alice")) as alice:
        r = alice.post("/api/volumes", files={"file": ("ball.nii.gz", small_nifti)})
        assert r.status_code == 201, r.text
        volume = r.json()["id"]
    folder = first.data_dir / "volumes" / volume  # all alice has: no models
    used = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
    first.stop(signal.SIGTERM)
    server = Server(first.data_dir, first.log, env={"MISS_QUOTA_MB": repr(used / 2**20)})
    try:
        with closing(_logged_in(server, "alice")) as alice:
            upload = alice.post("/api/volumes", files={"file": ("ball.nii.gz", small_nifti)})
            job = alice.post("/api/models", json={"volume": volume, "level": 0})
            huge = alice.post("/api/volumes", files={"file": ("big.nii.gz", b"0" * 2 * used)})
            kept = alice.get("/api/volumes").json()
        for refused, code in ((upload, 507), (job, 507), (huge, 413)):
            assert refused.status_code == code, refused.text
            assert "MISS_QUOTA_MB" in refused.json()["detail"], refused.text
        assert "delete volumes or models" in upload.json()["detail"]
        assert [v["id"] for v in kept] == [volume]
        assert _usage(server)["alice"]["bytes"] == used
    finally:
        server.stop(signal.SIGTERM)
