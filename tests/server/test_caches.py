"""What the server keeps in memory (``miss.server.storage.caches``) and what that must never
change: a deleted model or an ended session is gone at once, a running job's progress
is read afresh, a file served from memory is the file on disk, byte for byte."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import event, text
from starlette.responses import FileResponse

from miss.server.core.deps import here_or_threadpool
from miss.server.core.schemas import attachment
from miss.server.core.settings import Settings
from miss.server.storage.caches import ByteCaches, BytesLRU, RowCache
from miss.server.storage.db import POOL_SIZE, RUNNING
from miss.server.storage.store import Store

# -- the caches themselves ----------------------------------------------------------------


def test_bytes_lru_makes_once_and_forgets_the_least_recent() -> None:
    cache, made = BytesLRU(max_bytes=25), []

    def maker(key: str) -> bytes:
        made.append(key)
        return key.encode() * 10

    assert cache.get("a", lambda: maker("a")) == b"a" * 10
    assert cache.get("a", lambda: maker("a")) == b"a" * 10
    assert made == ["a"]  # the second time from the cache
    cache.get("b", lambda: maker("b"))
    cache.get("a", lambda: maker("a"))  # a is now the most recent
    cache.get("c", lambda: maker("c"))  # 30 bytes > 25: the least recent (b) goes
    cache.get("a", lambda: maker("a"))
    cache.get("b", lambda: maker("b"))
    assert made == ["a", "b", "c", "b"]
    cache.put("huge", b"x" * 26)  # larger than the whole budget: not kept
    assert cache.peek("huge") is None


def test_row_cache_expires_and_evicts() -> None:
    rows = RowCache(max_items=2, ttl=0.2)
    rows.put("a", 1, rows.generation)
    rows.put("b", 2, rows.generation)
    assert rows.get("a") == 1  # a is now the most recent
    rows.put("c", 3, rows.generation)  # over max_items: b goes
    assert (rows.get("a"), rows.get("b"), rows.get("c")) == (1, None, 3)
    time.sleep(0.25)
    assert rows.get("a") is None and rows.get("c") is None


def test_row_cache_never_keeps_a_row_read_before_a_drop() -> None:
    """The race the generation guards: a reader takes the old row, a writer commits and
    drops, then the reader puts its stale copy. The stale copy must not be kept."""
    rows = RowCache()
    seen = rows.generation
    stale = {"status": "done"}  # read before the writer's commit
    rows.drop("model")  # the writer, after its commit
    rows.put("model", stale, seen)
    assert rows.get("model") is None
    loaded = rows.cached("model", lambda: {"status": "fresh"}, lambda _: True)
    assert loaded == {"status": "fresh"} and rows.get("model") == loaded
    seen = rows.generation
    rows.clear()  # the same guard for everything at once
    rows.put("volume", {"owner": None}, seen)
    assert rows.get("model") is None and rows.get("volume") is None


def test_row_cache_keeps_only_what_keep_accepts() -> None:
    rows, loads = RowCache(), []

    def load() -> dict[str, str]:
        loads.append(1)
        return {"status": RUNNING}

    for _ in range(3):
        rows.cached("m", load, lambda row: row["status"] == "done")
    assert len(loads) == 3  # a running job's row is read afresh every time


def test_here_or_threadpool_runs_cached_work_on_the_loop_and_the_rest_in_a_thread() -> None:
    async def both() -> tuple[int, int, int]:
        here = await here_or_threadpool(True, threading.get_ident)
        there = await here_or_threadpool(False, threading.get_ident)
        return here, there, threading.get_ident()

    # A thread of its own: another test's browser session may have left a loop in this one.
    results: list[Any] = []
    runner = threading.Thread(target=lambda: results.append(asyncio.run(both())))
    runner.start()
    runner.join()
    here, there, loop_thread = results[0]
    assert here == loop_thread and there != loop_thread


def test_the_pool_keeps_its_connections(tmp_path: Path) -> None:
    """40 threads holding a connection at once, then querying over and over: no thread
    waits for the pool, and no connection is opened twice (an overflow connection would
    be opened again, pragmas and all, on every request)."""
    store = Store(tmp_path, Settings(data_dir=tmp_path).database_url)
    store.init()
    opened: list[int] = []
    errors: list[BaseException] = []
    event.listen(store.engine, "connect", lambda *_: opened.append(1))
    together = threading.Barrier(POOL_SIZE)

    def query() -> None:
        try:
            with store.session() as s:
                s.execute(text("SELECT 1"))
                together.wait(timeout=20)
            for _ in range(50):
                with store.session() as s:
                    s.execute(text("SELECT 1"))
        except BaseException as exc:
            errors.append(exc)

    try:
        threads = [threading.Thread(target=query) for _ in range(POOL_SIZE)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert not errors, errors[0]
        assert 0 < len(opened) <= POOL_SIZE
    finally:
        store.close()


# -- through the API ----------------------------------------------------------------------


@pytest.fixture
def done_model(
    make_client: Callable[..., TestClient],
    small_nifti: bytes,
    upload_for: Callable[..., dict[str, Any]],
    model_for: Callable[..., dict[str, Any]],
) -> tuple[TestClient, dict[str, Any]]:
    client = make_client()
    headers = dict(client.headers)
    volume = upload_for(client, headers, small_nifti, "Crâne ball.nii.gz")
    return client, model_for(client, headers, volume["id"])


def test_a_model_file_from_memory_is_the_file_on_disk(
    done_model: tuple[TestClient, dict[str, Any]],
) -> None:
    client, model = done_model
    store: Store = client.app.state.store
    path = store.model_dir(model["id"]) / "model.glb"
    first = client.get(f"/api/models/{model['id']}/model.glb")
    second = client.get(f"/api/models/{model['id']}/model.glb")  # from memory
    assert first.content == second.content == path.read_bytes()
    expected = FileResponse(path, filename=_name(first)).headers["content-disposition"]
    for r in (first, second):
        assert r.headers["content-disposition"] == expected
        assert r.headers["etag"] and r.headers["content-type"] == "model/gltf-binary"
        assert int(r.headers["content-length"]) == path.stat().st_size
    head = client.head(f"/api/models/{model['id']}/model.glb")
    assert head.status_code == 200 and head.content == b""
    assert head.headers["content-length"] == first.headers["content-length"]


def _name(response: Any) -> str:
    from urllib.parse import unquote

    value = response.headers["content-disposition"]
    if "filename*=" in value:
        return unquote(value.split("filename*=utf-8''", 1)[1])
    return value.split('filename="', 1)[1].rstrip('"')


def test_the_event_loop_never_waits_for_the_database(
    done_model: tuple[TestClient, dict[str, Any]],
) -> None:
    """A viewer's requests (the model, its GLB, slices), first with nothing cached (each look-up goes to the
    threadpool), then again (all answered from memory, on the loop): no query ever runs
    on the event loop's thread, and the second round asks the database nothing."""
    client, model = done_model
    store: Store = client.app.state.store
    # The job's own process and thread may still be ending (their last row updates drop
    # the row from the cache): the viewer comes once the worker is free again.
    deadline = time.monotonic() + 30
    while client.app.state.queue.health()["running"] and time.monotonic() < deadline:
        time.sleep(0.05)
    store.rows.clear()
    client.app.state.bytes = ByteCaches()  # nothing in memory
    on_loop: list[str] = []
    selects: list[str] = []

    def seen(_conn: Any, _cursor: Any, statement: str, *_: Any) -> None:
        if threading.current_thread().name.startswith("miss-jobs-"):
            return  # the job queue's own bookkeeping of the job just done: no viewer's
        try:
            asyncio.get_running_loop()
            on_loop.append(statement)
        except RuntimeError:  # a threadpool's (or the appender's) thread: no loop
            pass
        if statement.lstrip().upper().startswith("SELECT"):
            selects.append(statement)

    event.listen(store.engine, "before_cursor_execute", seen)
    try:
        m, v = f"/api/models/{model['id']}", f"/api/volumes/{model['volume']}"
        rounds = []
        for _ in range(2):
            selects.clear()
            for url in (m, f"{m}/model.glb", f"{v}/slices/axial/3.png", f"{m}/model.glb"):
                assert client.get(url).status_code == 200, url
            rounds.append(len(selects))
    finally:
        event.remove(store.engine, "before_cursor_execute", seen)
    assert on_loop == []
    assert rounds[0] > 0 and rounds[1] == 0, (rounds, selects)


def test_slices_render_a_core_at_a_time_while_the_loop_answers(
    done_model: tuple[TestClient, dict[str, Any]], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Many viewers asking for slices nobody rendered yet: at most ``RENDERS_AT_ONCE``
    renders run at a time (the threadpool's 40 at once kept the GIL from the event loop),
    and a cached model file is still answered meanwhile."""
    import miss.server.core.deps as deps
    from miss.server.volumes import imaging

    client, model = done_model
    monkeypatch.setattr(deps, "RENDERS_AT_ONCE", 2)
    client.app.state.__dict__.pop("renders", None)  # made again, with the patched size
    render, lock, state = imaging.render, threading.Lock(), {"now": 0, "most": 0}

    def slow_render(*args: Any, **kwargs: Any) -> bytes:
        with lock:
            state["now"] += 1
            state["most"] = max(state["most"], state["now"])
        try:
            time.sleep(0.05)
            return render(*args, **kwargs)
        finally:
            with lock:
                state["now"] -= 1

    monkeypatch.setattr(imaging, "render", slow_render)
    glb = f"/api/models/{model['id']}/model.glb"
    assert client.get(glb).status_code == 200  # now in memory
    urls = [f"/api/volumes/{model['volume']}/slices/axial/{i}.png" for i in range(12)]
    codes: list[int] = []
    threads = [
        threading.Thread(target=lambda u=u: codes.append(client.get(u).status_code)) for u in urls
    ]
    for t in threads:
        t.start()
    time.sleep(0.05)
    assert client.get(glb).status_code == 200  # while renders queue
    for t in threads:
        t.join()
    assert codes == [200] * len(urls)
    assert state["most"] == 2, state


def test_a_range_request_still_gets_the_range(
    done_model: tuple[TestClient, dict[str, Any]],
) -> None:
    client, model = done_model
    whole = client.get(f"/api/models/{model['id']}/model.glb").content
    part = client.get(f"/api/models/{model['id']}/model.glb", headers={"Range": "bytes=4-11"})
    assert part.status_code == 206 and part.content == whole[4:12]


def test_a_deleted_model_is_gone_at_once(done_model: tuple[TestClient, dict[str, Any]]) -> None:
    client, model = done_model
    url = f"/api/models/{model['id']}"
    for _ in range(2):  # now certainly in memory: the row and the file
        assert client.get(url).status_code == 200
        assert client.get(f"{url}/model.glb").status_code == 200
    assert client.delete(url).status_code == 204
    assert client.get(url).status_code == 404
    assert client.get(f"{url}/model.glb").status_code == 404


def test_a_deleted_volume_is_gone_at_once(done_model: tuple[TestClient, dict[str, Any]]) -> None:
    client, model = done_model
    volume = f"/api/volumes/{model['volume']}"
    for _ in range(2):
        assert client.get(volume).status_code == 200
        assert client.get(f"{volume}/slices/axial/3.png").status_code == 200
    assert client.delete(volume).status_code == 204
    assert client.get(volume).status_code == 404
    assert client.get(f"{volume}/slices/axial/3.png").status_code == 404
    assert client.get(f"/api/models/{model['id']}/model.glb").status_code == 404


def test_a_running_jobs_progress_is_read_afresh(
    done_model: tuple[TestClient, dict[str, Any]],
) -> None:
    """A worker is another process: what it writes must show at once, never a snapshot.
    (Only the server itself takes a finished model back, as when it queues a job again.)"""
    client, model = done_model
    store: Store = client.app.state.store
    url = f"/api/models/{model['id']}"
    assert client.get(url).json()["status"] == "done"  # a snapshot in memory now
    model_files = store.get_model(model["id"]).files
    # The server's own change, as when a job is claimed again: no files of the earlier run.
    store.update_model(model["id"], status=RUNNING, progress=0.0, files=None)
    assert client.get(f"{url}/model.glb").status_code == 409
    worker = Store(store.data_dir, store.database_url)  # as the worker process opens it
    try:
        for progress in (0.25, 0.5):
            worker.update_model(model["id"], progress=progress, durable=False)
            assert client.get(url).json()["progress"] == progress
        worker.update_model(model["id"], status="done", progress=1.0, files=model_files)
        assert client.get(url).json()["status"] == "done"
        assert client.get(f"{url}/model.glb").status_code == 200
    finally:
        worker.close()


def test_logging_out_ends_the_session_at_once(make_client: Callable[..., TestClient]) -> None:
    client = make_client()
    assert client.get("/api/volumes").status_code == 200  # the session, now in memory
    assert client.post("/api/auth/logout").status_code == 204
    r = client.get("/api/volumes")
    assert r.status_code == 401 and "log in" in r.json()["detail"]


def test_an_expired_session_is_refused_though_remembered(
    make_client: Callable[..., TestClient],
) -> None:
    client = make_client(session_hours=1.5 / 3600)  # 1.5 s
    assert client.get("/api/volumes").status_code == 200
    time.sleep(1.6)
    r = client.get("/api/volumes")
    assert r.status_code == 401 and "expired" in r.json()["detail"]


def test_download_audit_entries_are_there_for_the_next_request(
    done_model: tuple[TestClient, dict[str, Any]],
) -> None:
    """Committed after the response, but a later request in the same server sees them."""
    client, model = done_model
    for _ in range(5):
        assert client.get(f"/api/models/{model['id']}/model.stl").status_code == 200
    entries = client.get("/api/audit", params={"action": "download"}).json()
    mine = [e for e in entries if e["target"] == model["id"] and e["detail"] == {"format": "stl"}]
    assert len(mine) == 5
    assert all(e["at"] <= later["at"] for e, later in zip(mine, mine[1:], strict=False))


def test_an_older_models_table_gains_submitted_by(tmp_path: Path) -> None:
    """The job limit's column is added to a database from before it (and before Alembic)."""
    url = Settings(data_dir=tmp_path).database_url
    store = Store(tmp_path, url)
    store.init()
    with store.engine.begin() as con:
        con.execute(text("ALTER TABLE models DROP COLUMN submitted_by"))
        con.execute(text("ALTER TABLE models DROP COLUMN runner"))  # revision 0002's
        con.execute(text("DROP TABLE alembic_version"))
    store.close()
    store = Store(tmp_path, url)
    store.init()
    try:
        with store.engine.connect() as con:
            columns = {row[1] for row in con.execute(text("PRAGMA table_info(models)"))}
        assert "submitted_by" in columns
    finally:
        store.close()


def test_attachment_names_as_starlette_does() -> None:
    for name in ("plain-head_level300.glb", "Crâne_level300.glb", "a b;c.stl"):
        expected = FileResponse(__file__, filename=name).headers["content-disposition"]
        assert attachment(name) == {"Content-Disposition": expected}
