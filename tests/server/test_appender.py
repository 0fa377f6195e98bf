"""The audit log's writer (``miss.server.storage.appender``): one thread, many rows a commit,
nothing lost on a stop, nothing silently dropped on a failure."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import event, func, select

from miss.server.core.settings import Settings
from miss.server.storage.db import AuditRow, utcnow
from miss.server.storage.store import Store


@pytest.fixture
def store(tmp_path: Path) -> Iterator[Store]:
    s = Store(tmp_path, Settings(data_dir=tmp_path).database_url)
    s.init()
    yield s
    s.close()


def entry(n: int, actor: str | None = "tester") -> AuditRow:
    return AuditRow(at=utcnow(), action="view", actor=actor, target=f"m{n}", detail={})


def count(store: Store) -> int:
    with store.session() as s:
        return s.scalar(select(func.count()).select_from(AuditRow)) or 0


def test_not_started_it_commits_at_once(store: Store) -> None:
    store.appender.add(entry(1))
    assert count(store) == 1


def test_started_it_commits_many_rows_a_transaction(store: Store) -> None:
    commits: list[int] = []
    event.listen(store.light_engine, "commit", lambda _conn: commits.append(1))
    store.appender.start()

    def add(first: int) -> None:
        for n in range(first, first + 500):
            store.appender.add(entry(n))

    threads = [threading.Thread(target=add, args=(k * 500,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    store.appender.flush()
    assert count(store) == 2000
    assert 0 < len(commits) < 2000  # batched: fewer commits than rows
    with store.session() as s:
        targets = set(s.scalars(select(AuditRow.target)))
    assert targets == {f"m{n}" for n in range(2000)}


def test_stop_commits_what_is_still_queued(store: Store) -> None:
    store.appender.start()
    for n in range(300):
        store.appender.add(entry(n))
    store.appender.stop()  # no flush first
    assert count(store) == 300
    store.appender.add(entry(300))  # stopped: at once again
    assert count(store) == 301


def test_a_row_that_cannot_be_stored_is_logged_whole(
    store: Store, caplog: pytest.LogCaptureFixture
) -> None:
    """A batch with a bad row: the others are stored one by one, the bad one is logged
    with all its values, and the writer carries on."""
    with caplog.at_level(logging.ERROR, logger="miss.server.storage.appender"):
        store.appender._commit([entry(1), entry(2, actor=None), entry(3)])  # actor: NOT NULL
    assert "could not store a row" in caplog.text and "'target': 'm2'" in caplog.text
    with store.session() as s:
        assert set(s.scalars(select(AuditRow.target))) == {"m1", "m3"}
    store.appender.start()
    store.appender.add(entry(4, actor=None))
    store.appender.add(entry(5))
    store.appender.flush()
    assert count(store) == 3
