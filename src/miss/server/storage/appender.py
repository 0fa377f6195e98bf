"""One thread that commits rows for the whole server process, many per transaction."""

from __future__ import annotations

import logging
import queue
import threading
from typing import Any

from sqlalchemy.orm import sessionmaker

log = logging.getLogger("miss.server.storage.appender")


class Appender:
    """Rows added by one background thread, many per commit, after the request that
    made them has been answered: for the audit log, so that a viewer's download never
    waits for the database's write lock (held meanwhile by a worker, or by a commit
    stuck behind an upload being flushed to disk).

    Not started (the command line, a worker), ``add`` commits at once. Started (the
    server), a row is committed within milliseconds; a killed server loses the rows of
    those last milliseconds, a stopped one none (``stop`` waits for them). ``flush``
    waits until every row added before it is committed, so whoever reads the table in
    this process sees them. A row that cannot be committed is written to the log whole.
    """

    #: Rows per transaction at most.
    BATCH = 500

    def __init__(self, maker: sessionmaker) -> None:
        self.maker = maker
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._done = threading.Condition()
        self._added = self._committed = 0
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Commit from a thread of its own from now on (the server); idempotent."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="miss-appender", daemon=True)
            self._thread.start()

    def add(self, row: Any) -> None:
        """Commit ``row``: at once when not started, else within milliseconds from the thread."""
        if self._thread is None:
            self._commit([row])
            return
        with self._done:
            self._added += 1
        self._queue.put(row)

    @property
    def running(self) -> bool:
        """True once started: ``add`` only queues (it never waits for the database)."""
        return self._thread is not None

    def flush(self, timeout: float = 60.0) -> None:
        """Wait until every row added before this call is committed (at most ``timeout`` s)."""
        with self._done:
            wanted = self._added
            self._done.wait_for(lambda: self._committed >= wanted, timeout)

    def stop(self) -> None:
        """Commit the rows still queued and end the thread (waits up to 60 s)."""
        if self._thread is not None:
            self._queue.put(_STOP)
            self._thread.join(timeout=60)
            self._thread = None

    def _run(self) -> None:
        while True:
            batch = [self._queue.get()]
            while len(batch) < self.BATCH and not self._queue.empty():
                batch.append(self._queue.get())
            rows = [r for r in batch if r is not _STOP]
            stop = len(rows) < len(batch)
            self._commit(rows)
            with self._done:
                self._committed += len(rows)
                self._done.notify_all()
            if stop:
                return

    def _commit(self, rows: list[Any]) -> None:
        """One transaction; if it fails, each row on its own, so one bad row costs only
        itself (and goes to the log whole)."""
        if not rows:
            return
        try:
            with self.maker.begin() as s:
                s.add_all(rows)
            return
        except Exception:
            if len(rows) == 1:
                log.exception("could not store a row: %s", _describe(rows[0]))
                return
        for row in rows:
            self._commit([_copy(row)])


_STOP = object()


def _describe(row: Any) -> dict[str, Any]:
    return {c.key: getattr(row, c.key, None) for c in row.__table__.columns}


def _copy(row: Any) -> Any:
    """A fresh, unsaved row with the same values (a failed flush leaves ``row`` marked)."""
    values = {k: v for k, v in _describe(row).items() if v is not None}
    return type(row)(**values)
