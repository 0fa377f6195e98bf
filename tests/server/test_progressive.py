"""What a waiting physician sees first: a running job's preview and its GLB are listed and
served as soon as each is in place (the other formats and the error come later), and jobs
start in spare workers that loaded everything before the job came."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from support.server_app import running_row

from miss.demo import phantom
from miss.export import FORMATS
from miss.pipeline import PREVIEW, JobResult, run
from miss.server.core.schemas import model_out
from miss.server.core.settings import Settings
from miss.server.jobs import JobQueue
from miss.server.jobs import follow as followers
from miss.server.jobs.state import JobState
from miss.server.jobs.worker import DataFolder
from miss.server.storage import chunked
from miss.server.storage.store import Store
from miss.spec import JobSpec


def glb_triangles(data: bytes) -> int:
    """Triangles of a GLB, from its JSON chunk (index accessors' counts / 3)."""
    (length,) = struct.unpack_from("<I", data, 12)
    gltf = json.loads(data[20 : 20 + length])
    accessors = gltf["accessors"]
    return sum(
        accessors[p["indices"]]["count"] // 3 for m in gltf["meshes"] for p in m["primitives"]
    )


class Recorder:
    """A sink that notes what it got, in order, and whether the error was measured by then."""

    def __init__(self, wants_preview: bool) -> None:
        self.wants_preview = wants_preview
        self.put_order: list[str] = []
        self.files: dict[str, bytes] = {}
        self.delivered: JobResult | None = None

    def put(self, fmt: str, data: bytes) -> None:
        self.put_order.append(fmt)
        self.files[fmt] = data

    def deliver(self, result: JobResult) -> None:
        self.delivered = result


@pytest.mark.slow
def test_preview_first_then_glb_then_the_rest_then_the_error() -> None:
    head = phantom(128, spacing=1.5)  # 2.1 M voxels: big enough for a preview
    sink = Recorder(wants_preview=True)
    spec = JobSpec.of(level=300, formats=FORMATS)
    result = run(head, spec, sink=sink, export_options={"glb": {"compress": True}})
    sink.deliver(result)
    assert sink.put_order == [PREVIEW, "glb", *(f for f in FORMATS if f != "glb")]
    assert list(result.artifacts) == list(FORMATS)  # the asked order, as before
    assert result.report.max_error_mm is not None and result.report.max_error_mm > 0
    assert {"preview", "surface", "decimate", "write", "measure"} <= set(result.seconds)
    preview, model = glb_triangles(sink.files[PREVIEW]), glb_triangles(sink.files["glb"])
    assert 0 < preview < model / 2, (preview, model)


def test_no_preview_for_a_small_region_or_a_sink_that_wants_none() -> None:
    small = Recorder(wants_preview=True)
    run(phantom(48, spacing=4.0), JobSpec.of(level=300, formats=("stl", "glb")), sink=small)
    assert small.put_order == ["glb", "stl"]
    big = Recorder(wants_preview=False)
    run(phantom(128, spacing=1.5), JobSpec.of(level=300, formats=("glb",)), sink=big)
    assert big.put_order == ["glb"]


def test_a_running_jobs_preview_and_glb_are_served_before_it_is_done(
    client: TestClient, demo_id: str
) -> None:
    store: Store = client.app.state.store
    model_id = running_row(store, demo_id)
    state = JobState(store)
    folder = DataFolder(store.model_dir(model_id), state, model_id)
    assert client.get(f"/api/models/{model_id}").json()["preview"] is None
    assert client.get(f"/api/models/{model_id}/preview.glb").status_code == 404

    folder.put(PREVIEW, b"glTF preview bytes")
    body = client.get(f"/api/models/{model_id}").json()
    assert body["status"] == "running" and body["files"] is None
    r = client.get(body["preview"])
    assert r.status_code == 200 and r.content == b"glTF preview bytes"
    assert r.headers["content-type"] == "model/gltf-binary"

    folder.put("glb", b"glTF model bytes")
    body = client.get(f"/api/models/{model_id}").json()
    assert list(body["files"]) == ["glb"]
    r = client.get(body["files"]["glb"]["url"])
    assert r.status_code == 200 and r.content == b"glTF model bytes"
    r = client.get(f"/api/models/{model_id}/model.wrl")  # not written yet
    assert r.status_code == 409 and "running" in r.json()["detail"]

    folder.put("wrl", b"#VRML V2.0 utf8\n")
    assert state.finish(model_id, {"triangles": 1}, {"glb": folder.files["glb"]})
    body = client.get(f"/api/models/{model_id}").json()
    assert body["status"] == "done" and body["preview"] is None


def test_the_events_tell_a_file_put_in_place_before_the_next_read_of_the_row(
    client: TestClient, demo_id: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Between its reads of the job's row the stream looks at the model's folder (a stat):
    a GLB renamed into place is told at once. The row's reads are a minute apart here, so
    only the folder can tell it in time."""
    monkeypatch.setattr(followers, "EVENT_POLL", 60.0)
    store: Store = client.app.state.store
    model_id = running_row(store, demo_id)
    folder = DataFolder(store.model_dir(model_id), JobState(store), model_id)
    events: list[dict[str, Any]] = []

    def follow() -> None:
        with client.stream("GET", f"/api/models/{model_id}/events") as stream:
            for line in stream.iter_lines():
                if line.startswith("data:"):
                    events.append(json.loads(line[5:]))

    reader = threading.Thread(target=follow, daemon=True)
    reader.start()
    _until(lambda: len(events) >= 1)
    assert events[0]["status"] == "running" and events[0]["files"] is None
    folder.put("glb", b"glTF model bytes")
    _until(lambda: len(events) >= 2)
    assert list(events[1]["files"]) == ["glb"]
    assert client.delete(f"/api/models/{model_id}").status_code == 204  # the stream ends
    reader.join(timeout=20)
    assert not reader.is_alive() and events[-1]["status"] == "failed"


def test_streams_on_one_job_read_its_row_once_for_all(client: TestClient, demo_id: str) -> None:
    """Ten event streams on one running job (tabs, a room's guests, a flood) read its row
    as often as one stream does, not ten times as often; each still hears every change."""
    from sqlalchemy import event

    store: Store = client.app.state.store
    model_id = running_row(store, demo_id)
    folder = DataFolder(store.model_dir(model_id), JobState(store), model_id)
    reads: list[float] = []

    def seen(_conn: Any, _cursor: Any, statement: str, *_: Any) -> None:
        if statement.lstrip().upper().startswith("SELECT") and "FROM models" in statement:
            reads.append(time.monotonic())

    def reads_per_second(streams: int) -> tuple[float, list[list[dict[str, Any]]], list[Any]]:
        heard: list[list[dict[str, Any]]] = [[] for _ in range(streams)]

        def follow(n: int) -> None:
            with client.stream("GET", f"/api/models/{model_id}/events") as stream:
                for line in stream.iter_lines():
                    if line.startswith("data:"):
                        heard[n].append(json.loads(line[5:]))
                        if heard[n][-1]["status"] != "running":
                            return

        threads = [threading.Thread(target=follow, args=(n,), daemon=True) for n in range(streams)]
        for t in threads:
            t.start()
        _until(lambda: all(heard))
        reads.clear()
        time.sleep(1.5)
        rate = len(reads) / 1.5
        folder.put("glb", b"glTF model bytes")  # every stream hears it
        _until(lambda: all(any(e.get("files") for e in h) for h in heard))
        return rate, heard, threads

    event.listen(store.engine, "before_cursor_execute", seen)
    try:
        one, _, threads = reads_per_second(1)
        assert client.delete(f"/api/models/{model_id}").status_code == 204  # the streams end
        for t in threads:
            t.join(timeout=20)
        model_id = running_row(store, demo_id)
        folder = DataFolder(store.model_dir(model_id), JobState(store), model_id)
        ten, heard, threads = reads_per_second(10)
        assert client.delete(f"/api/models/{model_id}").status_code == 204
        for t in threads:
            t.join(timeout=20)
    finally:
        event.remove(store.engine, "before_cursor_execute", seen)
    assert one > 3, one  # the stream does read the row meanwhile (every 0.1 s)
    assert ten < 2 * one, (one, ten)  # the old streams: about 10x one's
    assert all(any(list(e.get("files") or []) == ["glb"] for e in h) for h in heard)


def _until(condition: Any, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert condition(), "not within 20 s"


def test_a_job_run_again_shows_nothing_of_its_earlier_attempt(data_dir: Path) -> None:
    store = Store(data_dir, Settings(data_dir=data_dir).database_url)  # no app, no queue
    try:
        model_id = running_row(store, store.list_volumes()[0].id)
        folder = DataFolder(store.model_dir(model_id), JobState(store), model_id)
        folder.put(PREVIEW, b"old preview")
        folder.put("glb", b"old model")
        assert JobState(store).requeue(model_id, count_attempt=True)  # as after a restart
        claimed = JobState(store).claim_next()
        assert claimed is not None and claimed.id == model_id
        assert claimed.files is None and claimed.stats is None
        assert model_out(claimed).preview is None and model_out(claimed).files is None
    finally:
        store.close()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie is dead for our purposes
    stat = Path(f"/proc/{pid}/stat").read_text().split()
    return stat[2] != "Z"


def _spare(client: TestClient, timeout: float = 30) -> Any:
    runner = client.app.state.queue.runner
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with runner._lock:
            if runner._ready:
                return runner._ready[0]
        time.sleep(0.05)
    raise AssertionError("no spare worker was started")


@pytest.mark.slow
def test_jobs_run_in_spare_workers_started_before_them(make_client: Any, wait_done: Any) -> None:
    client = make_client(demo=True, spare_workers=1)
    demo = client.get("/api/volumes").json()[0]["id"]
    spare = _spare(client)
    r = client.post("/api/models", json={"volume": demo, "level": 300, "sample_rate": 2})
    assert r.status_code == 202, r.text
    model_id = r.json()["id"]
    assert wait_done(client, model_id)["status"] == "done"
    store: Store = client.app.state.store
    log = (store.model_dir(model_id) / "worker.log").read_text()
    assert f"spare worker {spare.pid} " in log and f"takes job {model_id}" in log
    nxt = _spare(client)  # the next one is ready for the next job
    assert nxt.pid != spare.pid and _alive(nxt.pid)

    os.kill(nxt.pid, signal.SIGKILL)  # a spare that dies while waiting costs nothing
    r = client.post("/api/models", json={"volume": demo, "level": 400, "sample_rate": 2})
    assert wait_done(client, r.json()["id"])["status"] == "done"

    last = _spare(client)
    client.app.state.queue.stop()  # as when the server stops: no spare is left behind
    deadline = time.monotonic() + 10
    while _alive(last.pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(last.pid)


def _nice_of_threads(pid: int) -> dict[int, int]:
    """Each thread's nice value (field 19 of its stat; the name may hold spaces)."""
    nice = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):
            stat = (task / "stat").read_text()
            nice[int(task.name)] = int(stat.rsplit(")", 1)[1].split()[16])
    return nice


@pytest.mark.slow
def test_a_spares_warm_up_runs_below_the_job_it_waits_for(make_client: Any) -> None:
    """Issue 39: the next job's warm-up starts while a job runs; at the job's own priority
    it had taken half the cores from a small job. It runs in a thread at WARM_UP_NICE,
    while the thread that will run the job stays at WORKER_NICE."""
    from miss.server.jobs.process import WORKER_NICE
    from miss.server.jobs.worker import WARM_UP_NICE

    client = make_client(demo=False, spare_workers=1)
    spare = _spare(client)
    base = os.getpriority(os.PRIO_PROCESS, 0)
    seen: dict[int, int] = {}
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and len(set(seen.values())) < 2:
        seen = _nice_of_threads(spare.pid)
        time.sleep(0.02)
    assert seen.get(spare.pid) == min(19, base + WORKER_NICE), seen
    assert min(19, base + WARM_UP_NICE) in seen.values(), seen
    client.app.state.queue.stop()


def test_a_job_that_comes_early_waits_for_one_warm_up_step_not_all() -> None:
    """Issue 39: a job that came while its spare warmed up had waited, at WORKER_NICE,
    for the whole warm-up running at WARM_UP_NICE behind everything (1-2 s under load).
    It waits for the step under way; the job does the rest itself."""
    from miss.server.jobs.worker import warm_up_behind

    ran: list[str] = []
    inside, release = threading.Event(), threading.Event()

    def slow() -> None:
        inside.set()
        release.wait(10)
        ran.append("slow")

    warming = warm_up_behind([lambda: ran.append("first"), slow, lambda: ran.append("last")])
    assert inside.wait(10)
    warming.stop.set()  # the job comes
    release.set()
    warming.join(10)
    assert not warming.is_alive()
    assert ran == ["first", "slow"] and warming.done == 2


@pytest.mark.slow
def test_without_spares_each_job_starts_its_own_worker(make_client: Any, wait_done: Any) -> None:
    client = make_client(demo=True, spare_workers=0)
    demo = client.get("/api/volumes").json()[0]["id"]
    r = client.post("/api/models", json={"volume": demo, "level": 300, "sample_rate": 2})
    model_id = r.json()["id"]
    assert wait_done(client, model_id)["status"] == "done"
    assert client.app.state.queue.runner._ready == []
    log = (client.app.state.store.model_dir(model_id) / "worker.log").read_text()
    assert "spare worker" not in log
    assert np.isfinite(client.get(f"/api/models/{model_id}").json()["stats"]["max_error_mm"])


@pytest.mark.slow
def test_a_spare_worker_has_loaded_what_reading_a_stored_volume_needs(tmp_path: Path) -> None:
    """Reading the stored volume is the first thing a job does, before its preview: zarr's
    import there (0.4 s) came before every first pixel."""
    stored = tmp_path / "voxels"
    data = np.asfortranarray(np.arange(4 * 5 * 6, dtype=np.int16).reshape(4, 5, 6))
    chunked.write_array(stored, data, {"affine": np.eye(4).tolist()})
    probe = (
        "import sys\n"
        "from pathlib import Path\n"
        "from miss.server.jobs.worker import warm_up\n"
        "from miss.server.storage import chunked\n"
        "warm_up()\n"
        "before = set(sys.modules)\n"
        f"assert chunked.read(Path({str(stored)!r}), 1 << 20).sum() == {int(data.sum())}\n"
        "print(sorted(set(sys.modules) - before))\n"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


class _Runner:
    """Counts how often the queue asks for workers to be got ready."""

    def __init__(self) -> None:
        self.prepared = 0

    def start(self, model_id: str) -> Any:
        raise AssertionError("not used")

    def prepare(self) -> None:
        self.prepared += 1

    def close(self) -> None:
        return None


class _Worker:
    """A job's worker that ends when the test says so."""

    pid = 0

    def __init__(self) -> None:
        self.code: int | None = None

    def poll(self) -> int | None:
        return self.code

    def wait(self) -> int:
        while self.code is None:
            time.sleep(0.01)
        return self.code


def test_the_next_spare_starts_once_the_running_jobs_model_can_be_drawn(
    client: TestClient, demo_id: str
) -> None:
    """Not beside the job's first seconds (a spare's warm-up runs at the job's priority),
    not after the job (a job queued behind it would find no spare): at its GLB."""
    store: Store = client.app.state.store
    model_id = running_row(store, demo_id)
    runner, worker, ended = _Runner(), _Worker(), []
    queue = JobQueue(store, runner=runner)
    waiting = threading.Thread(target=lambda: ended.append(queue._wait(model_id, worker)))
    waiting.start()
    folder = DataFolder(store.model_dir(model_id), JobState(store), model_id)
    time.sleep(0.6)
    assert runner.prepared == 0  # computing: nothing to draw yet
    folder.put(PREVIEW, b"glTF preview bytes")
    time.sleep(0.6)
    assert runner.prepared == 0  # a preview is not the model
    folder.put("glb", b"glTF model bytes")
    deadline = time.monotonic() + 10
    while runner.prepared == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert runner.prepared == 1
    worker.code = 0
    waiting.join(timeout=10)
    assert ended == [0] and runner.prepared == 1


def test_a_job_is_still_waited_for_when_the_next_spare_cannot_start(
    client: TestClient, demo_id: str
) -> None:
    class Failing(_Runner):
        def prepare(self) -> None:
            raise OSError("Resource temporarily unavailable (fork)")

    store: Store = client.app.state.store
    model_id = running_row(store, demo_id)
    DataFolder(store.model_dir(model_id), JobState(store), model_id).put("glb", b"glTF")
    worker, ended = _Worker(), []
    waiting = threading.Thread(
        target=lambda: ended.append(JobQueue(store, runner=Failing())._wait(model_id, worker))
    )
    waiting.start()
    time.sleep(0.5)
    assert waiting.is_alive()  # still waiting for the worker
    worker.code = 0
    waiting.join(timeout=10)
    assert ended == [0]
