"""Fair use of the job workers (issue 39): one account's jobs never hold another's for
long, a job over its CPU or bytes-written limit fails with a message naming the limit
and leaves nothing behind, and an account over its disk quota is refused (507/413)."""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

from pg import copy_seed, settings_for
from realserver import serving

from miss.server.storage.db import QUEUED, ModelRow, utcnow
from miss.server.storage.store import Store, new_id
from miss.spec import JobSpec

DEMO = "Demo head phantom (synthetic CT)"


def _queue_rows(data: Path, jobs: list[tuple[str, float]]) -> list[str]:
    """Queued rows on the demo volume, oldest first: (account, level) each; no server
    runs yet, so the queue's order alone decides which starts when."""
    settings = settings_for(data)
    store = Store(data, settings.database_url)
    try:
        volume = next(v for v in store.list_volumes() if v.name == DEMO)
        first, ids = utcnow(), []
        for n, (account, level) in enumerate(jobs):
            spec = JobSpec.of(level=level, sample_rate=2, decimate="none")
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
