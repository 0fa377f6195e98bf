"""A job's life in its database row: queued -> running -> done | failed.

While running, the row also says what can already be shown: a preview (in ``stats``) and
the files written so far (``files``, the GLB first); ``done`` means every file is written
and the error measured.

Every change is a conditional UPDATE (``WHERE status = ...``), so the server's threads
and the worker processes can race without a lock: a claim, a finish or a failure
either applies to the state it expects or does nothing.
"""

from __future__ import annotations

from typing import Any

from sqlalchemy import func, select, update
from sqlalchemy.orm import aliased

from miss.server.jobs import turn
from miss.server.storage.db import DONE, FAILED, QUEUED, RUNNING, ModelRow, utcnow
from miss.server.storage.store import Store


def fair_order() -> tuple[Any, ...]:
    """ORDER BY terms for queued jobs: first the account whose latest job started longest
    ago (one that never started a job comes first), then the oldest job of it. An
    account is the name that queued the job (``submitted_by``; jobs without one, such as
    the demo's, share one turn)."""
    other = aliased(ModelRow)
    account = func.coalesce(ModelRow.submitted_by, "")
    last_start = (
        select(func.max(other.started_at))
        .where(func.coalesce(other.submitted_by, "") == account)
        .correlate(ModelRow)
        .scalar_subquery()
    )
    return (last_start.asc().nulls_first(), ModelRow.created_at, ModelRow.id)


class JobState:
    """State transitions of the model rows kept by ``store``."""

    def __init__(self, store: Store) -> None:
        self.store = store

    def claim_next(self, per_account: int = 0) -> ModelRow | None:
        """Mark the next queued job running and return it (None when the queue is empty).

        ``per_account`` (0: no cap) is the most jobs of one account this server process
        runs at once: an account whose jobs fill that many of its workers waits, so a
        worker is left for the next account's job even when the first account's jobs came
        first and are long (``MISS_WORKERS_PER_ACCOUNT``).

        The next job is the oldest queued one of the account served least recently
        (:func:`fair_order`): round robin between accounts, so one account's many jobs
        never hold another's behind more than one of theirs. The order comes from the
        rows alone, so every server process of one database agrees on it.

        One transaction reads and claims: on PostgreSQL the row is locked (``FOR UPDATE
        SKIP LOCKED``), so the threads of several server processes each take a different
        job without waiting on each other; on SQLite the write lock does the same. The
        ``status = queued`` condition stays, so a claim can never apply twice.
        """
        query = (
            select(ModelRow.id)
            .where(ModelRow.status == QUEUED, *self._room_for(per_account))
            .order_by(*fair_order())
            .limit(1)
            .with_for_update(skip_locked=True, of=ModelRow)
        )
        values = dict(
            status=RUNNING,
            progress=0.0,
            stage="starting",
            started_at=utcnow(),
            attempts=ModelRow.attempts + 1,
            error=None,
            stats=None,  # no preview nor files of an earlier, interrupted attempt
            files=None,
            runner=self.store.bus.origin,
        )
        while True:
            with self.store.session.begin() as s:
                model_id = s.scalars(query).first()
                if model_id is None:
                    return None
                claim = update(ModelRow).where(ModelRow.id == model_id, ModelRow.status == QUEUED)
                claimed = s.execute(claim.values(**values)).rowcount == 1
            self.store.rows.drop(("model", model_id))
            if claimed:
                return self.store.get_model(model_id)

    def _room_for(self, per_account: int) -> tuple[Any, ...]:
        """The WHERE term that keeps out accounts already running ``per_account`` jobs in
        this server process (none when ``per_account`` is 0)."""
        if per_account <= 0:
            return ()
        other = aliased(ModelRow)
        running = (
            select(func.count(other.id))
            .where(
                other.status == RUNNING,
                other.runner == self.store.bus.origin,
                func.coalesce(other.submitted_by, "") == func.coalesce(ModelRow.submitted_by, ""),
            )
            .correlate(ModelRow)
            .scalar_subquery()
        )
        return (running < per_account,)

    def others_waiting(self, model_id: str, account: str | None) -> int:
        """How many other jobs of ``account`` (who submitted ``model_id``) are queued or
        running, on any server process."""
        query = select(func.count(ModelRow.id)).where(
            ModelRow.status.in_((QUEUED, RUNNING)),
            ModelRow.id != model_id,
            func.coalesce(ModelRow.submitted_by, "") == (account or ""),
        )
        with self.store.session() as s:
            return s.scalar(query) or 0

    def status(self, model_id: str) -> str | None:
        """The job's status now, read from the database (None once its row is deleted)."""
        with self.store.session() as s:
            return s.scalar(select(ModelRow.status).where(ModelRow.id == model_id))

    def set_pid(self, model_id: str, pid: int | None) -> None:
        """Record the process id running the job (None: none runs it)."""
        self.store.update_model(model_id, pid=pid)

    def set_progress(self, model_id: str, stage: str, fraction: float) -> bool:
        """Record progress of a running job; False when it is no longer running (deleted)."""
        return self.store.update_model(
            model_id,
            ModelRow.status == RUNNING,
            durable=False,
            stage=stage,
            progress=float(min(max(fraction, 0.0), 1.0)),
        )

    def set_preview(self, model_id: str, preview: dict[str, Any]) -> bool:
        """Record a running job's preview (``preview.glb``: bytes, etag); it shows in the
        row's stats until the job is done. False when the job is no longer running."""
        return self.store.update_model(
            model_id, ModelRow.status == RUNNING, stats={"preview": preview}
        )

    def set_lod(self, model_id: str, lod: dict[str, Any], preview: dict[str, Any] | None) -> bool:
        """Record a running job's levels of detail (etag, bytes, tiles) beside its preview;
        False when the job is no longer running."""
        stats = {"lod": lod} | ({"preview": preview} if preview else {})
        return self.store.update_model(model_id, ModelRow.status == RUNNING, stats=stats)

    def set_files(self, model_id: str, files: dict[str, Any]) -> bool:
        """Record the files a running job has written so far (the GLB first: a viewer draws
        it while the rest are written); False when the job is no longer running."""
        return self.store.update_model(model_id, ModelRow.status == RUNNING, files=files)

    def finish(self, model_id: str, stats: dict[str, Any], files: dict[str, Any]) -> bool:
        """Mark the job done with its statistics and files; False when its row is no longer
        running (deleted or ended meanwhile)."""
        return self._ended(
            model_id,
            status=DONE,
            progress=1.0,
            stage="done",
            stats=stats,
            files=files,
            error=None,
            pid=None,
            finished_at=utcnow(),
        )

    def fail(self, model_id: str, reason: str, pid: int | None = None) -> bool:
        """Mark a running job failed with a reason a physician can act on; it lists no
        files nor preview (the failed run's are removed). With ``pid``, only while that
        worker still runs it: a supervisor never fails a run it did not start (the job
        finished, then was claimed again, before its worker's exit was seen)."""
        return self._ended(
            model_id,
            *([ModelRow.pid == pid] if pid is not None else []),
            status=FAILED,
            error=reason,
            pid=None,
            finished_at=utcnow(),
            files=None,
            stats=None,
        )

    def cancel(self, model_id: str, by: str) -> bool:
        """Stop a queued or running job at its owner's word (``by``, an account name): it
        ends failed with a reason saying so, and can be submitted again. False when it
        had ended already. A worker that runs it stops at its next report (``Stop``)."""
        reason = f"cancelled by {by}; submit the same parameters again to run it."
        values: dict[str, Any] = dict(status=FAILED, error=reason, pid=None, finished_at=utcnow())
        query = ModelRow.status.in_((QUEUED, RUNNING))
        ended = self.store.update_model(model_id, query, files=None, stats=None, **values)
        if ended:
            turn.done(self.store.model_dir(model_id))
        return ended

    def _ended(self, model_id: str, *where: Any, **values: Any) -> bool:
        """A running job's row (and ``where``) set to ``values``; its folder keeps no
        viewer's word."""
        ended = self.store.update_model(model_id, ModelRow.status == RUNNING, *where, **values)
        if ended:
            turn.done(self.store.model_dir(model_id))
        return ended

    def requeue(self, model_id: str, count_attempt: bool) -> bool:
        """Put a running job back in the queue; a clean shutdown does not count as an attempt."""
        values: dict[str, Any] = dict(status=QUEUED, progress=0.0, stage="", pid=None, runner=None)
        if not count_attempt:
            values["attempts"] = ModelRow.attempts - 1
        return self.store.update_model(model_id, ModelRow.status == RUNNING, **values)

    def recover(self, max_attempts: int = 2) -> tuple[list[str], list[str]]:
        """After a restart: re-queue jobs left running, fail those interrupted twice."""
        with self.store.session() as s:
            rows = list(s.scalars(select(ModelRow).where(ModelRow.status == RUNNING)))
        requeued, failed = [], []
        for row in rows:
            if row.attempts >= max_attempts:
                self.fail(
                    row.id,
                    f"interrupted twice (server stopped during {row.stage or 'the job'}); "
                    "submit the same parameters again to retry.",
                )
                failed.append(row.id)
            elif self.requeue(row.id, count_attempt=True):
                requeued.append(row.id)
        return requeued, failed

    def reap(self, max_attempts: int = 2) -> tuple[list[str], list[str]]:
        """Jobs whose server process is gone (several processes on PostgreSQL: its liveness
        lock is free): queued again, or failed once interrupted twice, as at a restart."""
        bus = self.store.bus
        query = select(ModelRow.runner).where(
            ModelRow.status == RUNNING, ModelRow.runner.is_not(None), ModelRow.runner != bus.origin
        )
        with self.store.session() as s:
            runners = set(s.scalars(query.distinct()))
        requeued: list[str] = []
        failed: list[str] = []
        for runner in runners:
            if bus.is_alive(runner):
                continue
            with self.store.session() as s:
                running = select(ModelRow).where(
                    ModelRow.status == RUNNING, ModelRow.runner == runner
                )
                rows = list(s.scalars(running))
            for row in rows:
                if row.attempts >= max_attempts:
                    reason = (
                        f"interrupted twice (its server process stopped during "
                        f"{row.stage or 'the job'}); submit the same parameters again to retry."
                    )
                    if self.fail(row.id, reason):
                        failed.append(row.id)
                elif self.store.update_model(
                    row.id,
                    ModelRow.status == RUNNING,
                    ModelRow.runner == runner,
                    status=QUEUED,
                    progress=0.0,
                    stage="",
                    pid=None,
                    runner=None,
                ):
                    requeued.append(row.id)
        return requeued, failed
