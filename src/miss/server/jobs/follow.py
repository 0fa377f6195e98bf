"""One look at a running job for everyone who follows it.

Each event stream of a running model (``GET /api/models/{id}/events``) used to read the
model's row ten times a second and stat its folder fifty times a second, on its own: ten
streams on one job (one account's tabs, a room's guests, or a flood of them) were a
hundred row reads a second, a fifth of a core. A :class:`Follower` does the looking once
per model, however many streams follow it, and wakes them when what they show changes.

The timing is the streams' own as before: the folder is looked at every
:data:`FOLDER_POLL` seconds (a stat, no database), the row is read at least every
:data:`EVENT_POLL` seconds, and after the folder changed (the worker renamed a file into
place: the preview, the GLB, the levels of detail) every :data:`FOLDER_POLL` seconds
until the row lists it, at most :data:`FOLLOW_READS` times.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from pathlib import Path

import anyio
from starlette.concurrency import run_in_threadpool

from miss.server.core.errors import NotFound
from miss.server.storage.db import DONE, FAILED, ModelRow
from miss.server.storage.store import Store

#: Seconds between reads of a job's row while it is followed (its stage and progress).
EVENT_POLL = 0.1
#: Seconds between looks at the model's folder meanwhile, and between reads of the row
#: once the folder changed, until the row lists what came (at most ``FOLLOW_READS``).
FOLDER_POLL = 0.02
FOLLOW_READS = 10

log = logging.getLogger(__name__)


def shown_state(row: ModelRow) -> tuple[object, ...]:
    """What a follower shows of the row: a change here is an event."""
    stats = row.stats or {}
    return (
        row.status,
        row.stage,
        round(row.progress, 3),
        str(stats.get("preview")),
        str(stats.get("lod")),
        str(row.files),
    )


def _mtime(folder: Path) -> int | None:
    """The folder's modification time, ns (a file created, renamed or removed in it
    changes it; appending to one does not); None while it does not exist."""
    try:
        return folder.stat().st_mtime_ns
    except OSError:
        return None


class Watch:
    """One model's row as last read, for its followers; ``row`` is None once the model
    was deleted. ``version`` counts the changes followers see."""

    def __init__(self, store: Store, row: ModelRow) -> None:
        self.store, self.model_id = store, row.id
        self.row: ModelRow | None = row
        self.version = 0
        self.followers = 0
        self._changed = asyncio.Event()
        self.task: asyncio.Task[None] | None = None

    def _set(self, row: ModelRow | None) -> bool:
        """Take the row as last read; True (the followers woken) when what they show changed."""
        before = self.row
        self.row = row
        if row is not None and before is not None and shown_state(row) == shown_state(before):
            return False
        self.version += 1
        self._changed.set()
        self._changed = asyncio.Event()
        return True

    async def changed(self, version: int, timeout: float) -> None:
        """Return once ``version`` is no longer the latest, or after ``timeout`` seconds."""
        if self.version != version:
            return
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._changed.wait(), timeout)

    def ended(self) -> bool:
        """Whether the job has ended (done or failed) or the model was deleted."""
        return self.row is None or self.row.status in (DONE, FAILED)

    async def run(self) -> None:
        """Read the row as the streams did, until the job ends or nobody follows."""
        model_id = self.model_id
        folder = self.store.model_dir(model_id)
        seen, follow = _mtime(folder), 0
        while not self.ended():
            if follow:  # the folder changed; the row will list what came
                follow -= 1
                await anyio.sleep(FOLDER_POLL)
            else:
                now = await _folder_change(folder, seen, EVENT_POLL)
                if now != seen:
                    seen, follow = now, FOLLOW_READS
            try:
                row = await run_in_threadpool(self.store.get_model, model_id)
            except NotFound:
                self._set(None)
                return
            except Exception:  # the database away a moment: the followers wait, not fail
                log.exception("following model %s", model_id)
                await anyio.sleep(EVENT_POLL)
                continue
            if self._set(row):
                follow = 0  # what came is listed


async def _folder_change(folder: Path, seen: int | None, timeout: float) -> int | None:
    """Wait until ``folder``'s modification time is no longer ``seen``, at most ``timeout``
    seconds; returns it then."""
    deadline = anyio.current_time() + timeout
    while True:
        await anyio.sleep(min(FOLDER_POLL, max(0.0, deadline - anyio.current_time())))
        now = _mtime(folder)
        if now != seen or anyio.current_time() >= deadline:
            return now


class Followers:
    """The watches of one server process's event loop, one per followed model."""

    def __init__(self) -> None:
        self._watches: dict[str, Watch] = {}

    @contextlib.asynccontextmanager
    async def follow(self, store: Store, row: ModelRow) -> AsyncIterator[Watch]:
        """The model's watch for as long as the caller follows it (started by the first
        follower, stopped after the last)."""
        watch = self._watches.get(row.id)
        if watch is None or watch.task is None or watch.task.done():
            watch = Watch(store, row)
            watch.task = asyncio.create_task(watch.run())
            self._watches[row.id] = watch
        watch.followers += 1
        try:
            yield watch
        finally:
            watch.followers -= 1
            if watch.followers == 0:
                if self._watches.get(row.id) is watch:
                    del self._watches[row.id]
                if watch.task is not None and not watch.task.done():
                    watch.task.cancel()

    def __len__(self) -> int:
        return len(self._watches)
