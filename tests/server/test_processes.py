"""Two ``miss serve`` processes on one PostgreSQL database and one data folder, as behind
a load balancer: what one changes the other sees at once (a revoked link closes a room
connection on the other within a second, a deleted model is 404 there at the next
request), a room's people on both see each other, and jobs submitted through both run
once each. Needs PostgreSQL (``tests/support/pg.py``) whatever ``MISS_TEST_DATABASE`` says."""

from __future__ import annotations

import json
import secrets
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families
from support import pg
from support.realserver import Server
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

pytestmark = pytest.mark.skipif(pg.missing() is not None, reason=str(pg.missing()))


@contextmanager
def two_servers(tmp_path: Path, **env: str) -> Iterator[tuple[Server, Server]]:
    """Two ``miss serve`` on one new database and one data folder; ``env``: more settings."""
    url = pg.shared().create(f"procs_{secrets.token_hex(4)}")
    env = {"MISS_DATABASE_URL": url, "MISS_DEMO": "0", "MISS_WORKERS": "2", **env}
    data = tmp_path / "data"
    servers: list[Server] = []
    try:
        for name in ("a", "b"):
            servers.append(Server(data, tmp_path / f"serve-{name}.log", workers=2, env=env))
        yield servers[0], servers[1]
    finally:
        for server in servers:
            if server.proc.poll() is None:
                server.stop(15)


@pytest.fixture
def two(tmp_path: Path) -> Iterator[tuple[Server, Server]]:
    with two_servers(tmp_path) as servers:
        yield servers


def ws_url(server: Server, model: str, query: str = "") -> str:
    return f"ws://127.0.0.1:{server.port}/ws/rooms/{model}{query}"


def until(ws: ClientConnection, kind: str, limit: int = 50) -> dict[str, Any]:
    for _ in range(limit):
        message = json.loads(ws.recv(timeout=10))
        if message["type"] == kind:
            return message
    raise AssertionError(f"no {kind!r} message in {limit}")


#: How long another process may take to hear of a change: PostgreSQL delivers the
#: notification after the change's commit, and the answer to the one who made it may
#: reach the test first (milliseconds; more on a loaded machine).
HEARD_WITHIN = 0.5


def seen_within(check: Callable[[], bool], seconds: float = HEARD_WITHIN) -> bool:
    """``check()`` true at once or within ``seconds`` (asked every 10 ms)."""
    deadline = time.monotonic() + seconds
    while not check():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def ball_model(a: Server, small_nifti: bytes) -> tuple[str, str]:
    r = a.http.post("/api/volumes", files={"file": ("ball.nii.gz", small_nifti)})
    assert r.status_code == 201, r.text
    volume = r.json()["id"]
    model = a.submit(volume, level=0, decimate="none")
    assert a.wait(model, ("done", "failed"))["status"] == "done"
    return volume, model


def test_people_on_two_processes_share_a_room(
    two: tuple[Server, Server], small_nifti: bytes
) -> None:
    """The owner on A, a guest (share link) on B: presence, pins, chat and following the
    presenter's view reach the other process; the pin is in the room's state on both."""
    a, b = two
    _, model = ball_model(a, small_nifti)
    lo, hi = a.model(model)["stats"]["bounds_mm"]
    centre = [(p + q) / 2 for p, q in zip(lo, hi, strict=True)]
    token = a.http.post("/api/shares", json={"model": model, "can_annotate": True})
    token = token.json()["url"][3:]
    owner_headers = {"Authorization": f"Bearer {a.token}"}
    with connect(ws_url(a, model), additional_headers=owner_headers, open_timeout=30) as owner:
        assert until(owner, "welcome")["you"]["name"] == "admin"
        with connect(ws_url(b, model, f"?share={token}&name=Lee"), open_timeout=30) as guest:
            assert until(guest, "welcome")["you"]["name"] == "Lee (guest)"
            assert until(owner, "joined")["participant"]["name"] == "Lee (guest)"
            assert until(guest, "joined")["participant"]["name"] == "admin"  # B asked A

            guest.send(json.dumps({"type": "pin", "model": model, "point": centre, "note": "here"}))
            assert until(owner, "pin")["item"]["note"] == "here"
            owner.send(json.dumps({"type": "chat", "text": "seen it"}))
            assert until(guest, "chat")["item"]["text"] == "seen it"

            owner.send(json.dumps({"type": "presenter", "on": True}))
            assert until(guest, "presenter")["name"] == "admin"
            view = {"position": [0, -300, 0], "target": centre, "up": [0, 0, 1]}
            owner.send(json.dumps({"type": "camera", **view}))
            assert until(guest, "camera")["position"] == [0, -300, 0]

            headers = {"Authorization": f"Bearer {a.token}"}
            with connect(ws_url(b, model), additional_headers=headers, open_timeout=30) as late:
                welcome = until(late, "welcome")  # a later joiner on B: state from both
                assert [p["note"] for p in welcome["pins"]] == ["here"]
                assert [c["text"] for c in welcome["chat"]] == ["seen it"]
                assert {p["name"] for p in welcome["participants"]} >= {"admin", "Lee (guest)"}
                assert welcome["view"] is not None and welcome["presenter"]


def test_a_revoked_link_closes_a_guest_on_the_other_process(
    two: tuple[Server, Server], small_nifti: bytes
) -> None:
    a, b = two
    _, model = ball_model(a, small_nifti)
    r = a.http.post("/api/shares", json={"model": model, "can_annotate": True})
    share, token = r.json()["id"], r.json()["url"][3:]
    with connect(ws_url(b, model, f"?share={token}&name=Lee"), open_timeout=30) as guest:
        assert json.loads(guest.recv(timeout=10))["type"] == "welcome"
        start = time.monotonic()
        assert a.http.delete(f"/api/shares/{share}").status_code == 204
        with pytest.raises(ConnectionClosed) as closed:
            while True:
                guest.recv(timeout=5)
        assert time.monotonic() - start < 1.0
        assert closed.value.rcvd is not None and closed.value.rcvd.code == 4410


def test_a_model_deleted_through_one_is_gone_from_the_other(
    two: tuple[Server, Server], small_nifti: bytes
) -> None:
    a, b = two
    _, model = ball_model(a, small_nifti)
    for server in (a, b):  # both hold the finished model's row and file in memory
        assert server.http.get(f"/api/models/{model}").status_code == 200
        assert server.http.get(f"/api/models/{model}/model.glb").status_code == 200
    assert b.http.delete(f"/api/models/{model}").status_code == 204
    assert seen_within(lambda: a.http.get(f"/api/models/{model}").status_code == 404)
    assert a.http.get(f"/api/models/{model}/model.glb").status_code == 404


def test_logout_and_password_reset_through_one_end_sessions_on_the_other(
    two: tuple[Server, Server],
) -> None:
    """Sessions are cached by each process (``RowCache``): the other's drop reaches it."""
    a, b = two
    r = a.http.post("/api/users", json={"name": "ann", "password": "ann-password"})
    assert r.status_code == 201, r.text

    def session() -> dict[str, str]:
        body = {"username": "ann", "password": "ann-password"}
        r = httpx.post(f"{a.url}/api/auth/login", json=body)
        return {"Authorization": f"Bearer {r.json()['token']}"}

    ann = session()
    assert b.http.get("/api/volumes", headers=ann).status_code == 200  # cached on B
    assert a.http.post("/api/auth/logout", headers=ann).status_code == 204
    assert seen_within(lambda: b.http.get("/api/volumes", headers=ann).status_code == 401)

    ann = session()
    assert b.http.get("/api/volumes", headers=ann).status_code == 200
    r = a.http.patch("/api/users/ann", json={"password": "a-new-password"})
    assert r.status_code == 200, r.text
    assert seen_within(lambda: b.http.get("/api/volumes", headers=ann).status_code == 401)


def test_jobs_submitted_through_both_run_once_each(
    two: tuple[Server, Server], small_nifti: bytes
) -> None:
    a, b = two
    volume, _ = ball_model(a, small_nifti)
    jobs = [
        (a if n % 2 else b).submit(volume, level=-900 + 90 * n, decimate="none") for n in range(20)
    ]
    assert len(set(jobs)) == 20
    done = [a.wait(job, ("done", "failed"), timeout=300) for job in jobs]
    assert [d["status"] for d in done] == ["done"] * 20
    assert [d["attempts"] for d in done] == [1] * 20  # each claim counts one attempt


def test_a_job_of_a_killed_process_is_run_by_the_other(tmp_path: Path) -> None:
    """A kills -9 while its worker computes: B queues the job again (A's liveness lock is
    free) within seconds and runs it to the end, as a restart would."""
    import gzip

    import nibabel as nib
    import numpy as np

    url = pg.shared().create(f"procs_{secrets.token_hex(4)}")
    env = {"MISS_DATABASE_URL": url, "MISS_DEMO": "0", "MISS_SPARE_WORKERS": "0"}
    data = tmp_path / "data"
    # Noise at level 0 crosses nearly every cell: ~8 M triangles, several seconds of work
    # even on a quiet machine, longer than B takes to start (64³ once ended first in CI).
    noise = np.random.default_rng(0).integers(-1000, 1000, (128, 128, 128)).astype(np.int16)
    content = gzip.compress(nib.Nifti1Image(noise, np.eye(4)).to_bytes(), compresslevel=1)
    a = Server(data, tmp_path / "serve-a.log", env=env)
    b = None
    try:
        r = a.http.post("/api/volumes", files={"file": ("noise.nii.gz", content)})
        assert r.status_code == 201, r.text
        job = a.submit(r.json()["id"], level=0, decimate="none")
        assert a.wait(job, ("running",))["attempts"] == 1  # A's, before B is there
        b = Server(data, tmp_path / "serve-b.log", env=env)
        assert a.model(job)["status"] == "running", "the job ended too soon: make it longer"
        a.proc.kill()
        a.proc.wait()
        start = time.monotonic()
        deadline = time.monotonic() + 60
        while (body := b.model(job))["attempts"] < 2:
            assert time.monotonic() < deadline, body
            time.sleep(0.1)
        assert time.monotonic() - start < 15
        assert b.wait(job, ("done", "failed"), timeout=300)["status"] == "done"
    finally:
        for server in (a, b):
            if server is not None and server.proc.poll() is None:
                server.stop(15)


def test_serve_processes_answers_from_several(tmp_path: Path) -> None:
    """``miss serve --processes 2``: one port, two processes, one database."""
    url = pg.shared().create(f"procs_{secrets.token_hex(4)}")
    env = {"MISS_DATABASE_URL": url, "MISS_DEMO": "0"}
    server = Server(tmp_path / "data", tmp_path / "serve.log", env=env, args=["--processes", "2"])
    try:
        seen = set()
        for _ in range(40):  # a new connection each time
            with httpx.Client(base_url=server.url, headers=server.http.headers) as fresh:
                r = fresh.get("/api/health?deep=1")
            assert r.status_code == 200, r.text
            seen.add(r.json()["process"])
        assert len(seen) == 2, seen
    finally:
        server.stop(15)


def test_a_rooms_cap_counts_its_people_on_every_process(tmp_path: Path, small_nifti) -> None:
    """MISS_ROOM_MAX_PEOPLE=2: one person on A, one on B, and a third on either is
    refused, room full (each process alone would have let them in)."""
    with two_servers(tmp_path, MISS_ROOM_MAX_PEOPLE="2") as (a, b):
        _, model = ball_model(a, small_nifti)
        headers = {"Authorization": f"Bearer {a.token}"}
        with connect(ws_url(a, model), additional_headers=headers, open_timeout=30) as first:
            mine = until(first, "welcome")["you"]["id"]
            with connect(ws_url(b, model), additional_headers=headers, open_timeout=30) as second:
                welcome = until(second, "welcome")
                until(first, "joined")  # A has heard of B's person
                if mine not in {p["id"] for p in welcome["participants"]}:
                    # B hears of A's person when A answers the room's hello
                    assert until(second, "joined")["participant"]["id"] == mine
                for server in (a, b):
                    with connect(
                        ws_url(server, model), additional_headers=headers, open_timeout=30
                    ) as third:
                        refused = until(third, "error")
                        assert refused["code"] == "full" and "2 people" in refused["error"]
                        with pytest.raises(ConnectionClosed) as closed:
                            third.recv(timeout=10)
                        assert closed.value.rcvd.code == 4429


def test_people_on_a_process_that_dies_leave_the_room_elsewhere(
    two: tuple[Server, Server], small_nifti: bytes
) -> None:
    """B killed (no time to say its people left): A's people hear them leave within a
    few seconds (B's liveness lock is free), and the room's cap no longer counts them."""
    a, b = two
    _, model = ball_model(a, small_nifti)
    headers = {"Authorization": f"Bearer {a.token}"}
    with connect(ws_url(a, model), additional_headers=headers, open_timeout=30) as here:
        until(here, "welcome")
        with connect(ws_url(b, model), additional_headers=headers, open_timeout=30) as there:
            theirs = until(there, "welcome")["you"]["id"]
            assert until(here, "joined")["participant"]["id"] == theirs
            b.proc.kill()
            b.proc.wait()
            start = time.monotonic()
        left = until(here, "left")
        assert left["id"] == theirs and time.monotonic() - start < 10
        with connect(ws_url(a, model), additional_headers=headers, open_timeout=30) as late:
            people = until(late, "welcome")["participants"]
        assert theirs not in {p["id"] for p in people}


def samples(server: Server) -> dict[tuple[str, frozenset[tuple[str, str]]], float]:
    r = server.http.get("/metrics")
    assert r.status_code == 200, r.text
    return {
        (s.name, frozenset(s.labels.items())): s.value
        for family in text_string_to_metric_families(r.text)
        for s in family.samples
    }


def test_metrics_of_either_process_sum_both(two: tuple[Server, Server], small_nifti: bytes) -> None:
    """Requests through A and B counted once each in ``/metrics`` of either; room
    connections summed over the running processes; B killed: its requests still count,
    its connections no longer."""
    a, b = two
    _, model = ball_model(a, small_nifti)
    missing = "/api/models/0000000000000000"
    for server, n in ((a, 3), (b, 5)):
        for _ in range(n):
            assert server.http.get(missing).status_code == 404
    route = frozenset({("method", "GET"), ("route", "/api/models/{model_id}")})
    not_found = ("miss_http_requests_total", route | {("status", "404")})
    rooms = ("miss_room_connections", frozenset())
    for server in (a, b):
        got = samples(server)
        assert got[not_found] == 8
        assert got[("miss_http_request_seconds_count", route)] >= 8
        assert got[rooms] == 0
    headers = {"Authorization": f"Bearer {b.token}"}
    with connect(ws_url(b, model), additional_headers=headers, open_timeout=30) as ws:
        until(ws, "welcome")
        assert samples(a)[rooms] == 1
    assert seen_within(lambda: samples(a)[rooms] == 0)
    with connect(ws_url(b, model), additional_headers=headers, open_timeout=30) as ws:
        until(ws, "welcome")
        assert samples(a)[rooms] == 1
        b.proc.kill()  # no time to leave the room or remove its files
        b.proc.wait()
    got = samples(a)
    assert got[not_found] == 8 and got[rooms] == 0


#: The API's burst in the next test; no refill to speak of while it runs.
BURST = 40


def test_the_api_limit_holds_across_processes(tmp_path: Path) -> None:
    """One account hammering A and B in turn is let through about one burst in all, not
    a burst on each (what A let through is taken from B's bucket and back within
    ``ratelimit.SHARE_EVERY``); then both refuse, and keep refusing."""
    with two_servers(tmp_path, MISS_API_RATE="0.01", MISS_API_BURST=str(BURST)) as (a, b):
        answers = [
            (a if n % 2 else b).http.get("/api/models/0000000000000000").status_code
            for n in range(3 * BURST)
        ]
        assert set(answers) == {404, 429}, answers
        let_through = answers.count(404)
        assert BURST <= let_through <= BURST * 1.5, answers  # one process each: 2 * BURST
        time.sleep(0.3)  # each has heard all the other let through
        for server in (a, b):
            assert server.http.get("/api/volumes").status_code == 429
