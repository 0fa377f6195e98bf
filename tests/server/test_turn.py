"""The viewer's turn (``miss.server.jobs.turn``): a job whose model can be drawn holds back
its other work while a viewer that follows it has not drawn it yet, at most ``HOLD``."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from support.server_app import running_row

from miss.demo import phantom
from miss.export import FORMATS
from miss.pipeline import run
from miss.server.jobs import JobQueue, turn
from miss.server.jobs.state import JobState
from miss.server.jobs.worker import DataFolder
from miss.server.storage.store import Store, new_id
from miss.spec import JobSpec


def test_held_only_while_a_viewer_follows_and_has_not_drawn_it(tmp_path: Path) -> None:
    now = time.time()
    assert not turn.held(tmp_path, now, now)  # nobody follows the job
    turn.watching(tmp_path)
    assert turn.held(tmp_path, now, now + 0.1)
    assert not turn.held(tmp_path, now, now + turn.HOLD)  # waited long enough
    watched = tmp_path / turn.WATCHED
    os.utime(watched, (now - turn.FRESH - 1, now - turn.FRESH - 1))
    assert not turn.held(tmp_path, now, now + 0.1)  # the viewer went away
    turn.watching(tmp_path)
    turn.shown(tmp_path)
    assert not turn.held(tmp_path, now, now + 0.1)  # drawn
    turn.forget(tmp_path)  # a new attempt at the job
    assert turn.held(tmp_path, now, now + 0.1)


def test_watching_never_makes_a_deleted_models_folder_again(tmp_path: Path) -> None:
    turn.watching(tmp_path / "gone")
    turn.shown(tmp_path / "gone")
    assert not (tmp_path / "gone").exists()


def test_done_leaves_neither_file(tmp_path: Path) -> None:
    turn.watching(tmp_path)
    turn.shown(tmp_path)
    turn.done(tmp_path)
    assert list(tmp_path.iterdir()) == []
    turn.done(tmp_path)  # nothing there: nothing to do
    turn.done(tmp_path / "gone")
    assert not (tmp_path / "gone").exists()


def _follow(client: TestClient, url: str) -> list[str]:
    """Read the event stream at ``url`` in a thread; its data lines, as they come."""
    events: list[str] = []

    def follow() -> None:
        with client.stream("GET", url) as stream:
            events.extend(line for line in stream.iter_lines() if line.startswith("data:"))

    threading.Thread(target=follow, daemon=True).start()
    return events


def _followed_job(
    client: TestClient, demo_id: str, draws: bool
) -> tuple[Store, str, DataFolder, list[str]]:
    """A running job with its preview, followed by an event stream (a viewer's, drawing
    the model, with ``draws``; then once the stream says so by ``.watched``)."""
    store: Store = client.app.state.store
    model_id = running_row(store, demo_id)
    folder = DataFolder(store.model_dir(model_id), JobState(store), model_id)
    folder.put("preview", b"glTF preview")  # the runner would have made the folder
    events = _follow(client, f"/api/models/{model_id}/events{'?draws=1' if draws else ''}")
    deadline = time.monotonic() + 20
    while not (folder.folder / turn.WATCHED).exists() if draws else not events:
        assert time.monotonic() < deadline
        time.sleep(0.02)
    return store, model_id, folder, events


def test_a_job_holds_back_until_the_viewer_following_it_says_it_drew_the_model(
    client: TestClient, demo_id: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The page's event stream says a viewer follows the job; the job, its GLB in place,
    waits (a minute at most here) until the page posts that it drew the model; the queue
    starts no spare meanwhile."""
    monkeypatch.setattr(turn, "HOLD", 60.0)
    store, model_id, folder, _ = _followed_job(client, demo_id, draws=True)
    assert (folder.folder / turn.WATCHED).exists()

    folder.put("glb", b"glTF model")
    waited: list[float] = []
    job = threading.Thread(target=lambda: waited.append(folder.wait_for_viewer()))
    job.start()
    job.join(timeout=1.0)
    assert job.is_alive()  # held: the viewer has not drawn it
    assert not JobQueue(store)._drawable(model_id)  # nor does a spare warm up meanwhile

    assert client.post(f"/api/models/{model_id}/shown").status_code == 204
    job.join(timeout=20)
    assert not job.is_alive() and 1.0 <= waited[0] < 20
    assert JobQueue(store)._drawable(model_id)
    assert client.delete(f"/api/models/{model_id}").status_code == 204


def test_nobody_drawing_the_model_holds_nothing(client: TestClient, demo_id: str) -> None:
    """A follower that does not draw the model (a script: no ``draws=1``) holds no job."""
    store, model_id, folder, events = _followed_job(client, demo_id, draws=False)
    time.sleep(0.5)  # several looks at the job since
    assert events and not (folder.folder / turn.WATCHED).exists()
    folder.put("glb", b"glTF model")
    assert folder.wait_for_viewer() == 0.0
    assert JobQueue(store)._drawable(model_id)
    # a word for a model that is not running changes nothing
    other = client.post(f"/api/models/{model_id}/shown")
    assert other.status_code == 204
    assert client.delete(f"/api/models/{model_id}").status_code == 204
    assert client.post(f"/api/models/{model_id}/shown").status_code == 404


def test_someone_elses_model_cannot_be_said_drawn(client: TestClient, demo_id: str) -> None:
    anonymous: Any = TestClient(client.app)
    r = anonymous.post(f"/api/models/{new_id()}/shown")
    assert r.status_code in (401, 403, 404) and "detail" in r.json()


class _Waiting:
    """A sink whose viewer takes a second to draw the model; notes what came when."""

    wants_preview, lod_triangles = False, None

    def __init__(self) -> None:
        self.order: list[str] = []

    def put(self, fmt: str, data: bytes) -> None:
        self.order.append(fmt)

    def put_lod(self, files: Any) -> None:
        raise AssertionError("not used")

    def wait_for_viewer(self) -> float:
        self.order.append("viewer")
        time.sleep(1.0)
        return 1.0

    def deliver(self, result: Any) -> None:
        return None


def test_the_job_waits_for_the_viewer_after_its_glb_and_before_the_rest() -> None:
    sink = _Waiting()
    result = run(phantom(48, spacing=4.0), JobSpec.of(level=300, formats=FORMATS), sink=sink)
    assert sink.order == ["glb", "viewer", *(f for f in FORMATS if f != "glb")]
    # the wait is told as such, not as writing (a small phantom's files take milliseconds)
    assert result.seconds["viewer"] == 1.0 and result.seconds["write"] < 0.9


@pytest.mark.parametrize("end", ["finish", "fail"])
def test_an_ended_jobs_folder_keeps_no_viewers_word(
    client: TestClient, demo_id: str, end: str
) -> None:
    """A job followed and drawn by its viewer ends (done or failed): its folder keeps
    neither ``.watched`` nor ``.shown``, once the row says so and once the viewer's event
    stream has ended."""
    store, model_id, folder, events = _followed_job(client, demo_id, draws=True)
    folder.put("glb", b"glTF model")
    assert client.post(f"/api/models/{model_id}/shown").status_code == 204
    assert (folder.folder / turn.WATCHED).exists() and (folder.folder / turn.SHOWN).exists()

    state = JobState(store)
    assert state.finish(model_id, {}, {}) if end == "finish" else state.fail(model_id, "no")
    assert not (folder.folder / turn.WATCHED).exists()
    assert not (folder.folder / turn.SHOWN).exists()
    status = "done" if end == "finish" else "failed"
    deadline = time.monotonic() + 20
    while not any(f'"status":"{status}"' in e.replace(" ", "") for e in events):
        assert time.monotonic() < deadline, events
        time.sleep(0.02)
    time.sleep(0.3)  # the stream's own end, after its last word
    assert sorted(p.name for p in folder.folder.iterdir()) == ["model.glb", "preview.glb"]
    assert client.delete(f"/api/models/{model_id}").status_code == 204
