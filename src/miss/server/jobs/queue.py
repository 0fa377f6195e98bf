"""The job queue: threads in the server that each supervise one worker process at a time.

State lives in the database, not in these threads: a thread claims the oldest queued
row, starts ``python -m miss.server.jobs.worker`` for it and waits. The child writes
progress and the result; when it dies by a signal (a segfault in native code, the
out-of-memory killer) the thread records why, reading the worker's log for the signs of
an allocation that failed in native code. On start, rows left ``running`` by a previous
server are queued again, or failed once they were interrupted twice.

Workers inherit the server's environment, so ``MISS_WORKER_MEMORY_MB`` reaches them
(see ``miss.server.jobs.worker``), and get the job limits of the server's settings
(``MISS_JOB_CPU_SECONDS``, ``MISS_JOB_WRITE_MB``). A worker ended by the kernel at its
CPU limit (SIGXCPU) fails its job with a message naming the limit; any job that fails
leaves no model files behind.

Which queued job runs next is round robin between accounts (``JobState.claim_next``).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable

from miss.server.jobs import turn
from miss.server.jobs.process import Runner, Running, WorkerProcess, crash_reason, read_log
from miss.server.jobs.state import JobState
from miss.server.storage.db import FAILED, RUNNING, ModelRow
from miss.server.storage.store import LOD_DIR, Store, remove_outputs

log = logging.getLogger("miss.server.jobs")

MAX_ATTEMPTS = 2
#: Seconds an idle thread sleeps before looking at the database again (jobs queued by
#: another process, or a wake-up missed).
POLL_SECONDS = 2.0
#: How often a job's thread looks whether its model can be drawn yet (then the next spare
#: worker starts warming up).
DRAWABLE_POLL_SECONDS = 0.25
#: Seconds between looks for jobs of server processes that are gone (PostgreSQL only).
REAP_SECONDS = 5.0


def yielded(pid: int) -> bool:
    """Whether worker ``pid`` has dropped to SCHED_IDLE (its own decision, not asked again
    of the database); False where that cannot be seen."""
    try:
        return os.sched_getscheduler(pid) == os.SCHED_IDLE
    except (OSError, AttributeError):  # ended meanwhile, or not Linux
        return False


class JobQueue:
    """``workers`` threads running queued jobs, each through the runner (by default a
    :class:`WorkerProcess`: one child process a job)."""

    def __init__(
        self,
        store: Store,
        workers: int = 1,
        runner: Runner | None = None,
        cpu_seconds: float = 0.0,
        per_account: int = 0,
    ) -> None:
        self.store = store
        #: Jobs of one account run at once here at most (0: no cap; see ``claim_next``).
        self.per_account = per_account
        #: The CPU limit of one job (``MISS_JOB_CPU_SECONDS``), for the message.
        self.cpu_seconds = cpu_seconds
        self.state = JobState(store)
        self.workers = workers
        self.runner = runner or WorkerProcess(store)
        self._wake = threading.Condition()
        self._stopping = threading.Event()
        self._threads: list[threading.Thread] = []
        self._running: dict[str, Running] = {}
        self._reaper: threading.Thread | None = None
        #: Told each job's outcome ("done", "failed", "requeued") and wall time, seconds.
        self.on_finished: Callable[[str, float], None] = lambda outcome, seconds: None

    def health(self) -> dict[str, object]:
        """For ``/api/health?deep=1``: the threads alive, the jobs they run now."""
        alive = sum(t.is_alive() for t in self._threads)
        return {
            "ok": alive == self.workers and not self._stopping.is_set(),
            "alive": alive,
            "of": self.workers,
            "running": len(self._running),
        }

    def start(self) -> None:
        """Recover interrupted jobs, start the threads (the store holds the folder's lock).

        Only a server that starts alone recovers: beside other servers of the same
        database, the jobs marked running are theirs. Jobs queued by another server wake
        a thread here at once (the bus); else a thread looks every ``POLL_SECONDS``."""
        if self.store.alone:
            requeued, failed = self.state.recover(MAX_ATTEMPTS)
            if requeued or failed:
                log.warning(
                    "after restart: %d job(s) queued again, %d failed", len(requeued), len(failed)
                )
        self.store.bus.subscribe("jobs", lambda _data: self.wake())
        for n in range(self.workers):
            thread = threading.Thread(target=self._loop, name=f"miss-jobs-{n}", daemon=True)
            thread.start()
            self._threads.append(thread)
        if self.store.shared:
            self._reaper = threading.Thread(target=self._reap, name="miss-jobs-reap", daemon=True)
            self._reaper.start()

    def submit(self) -> None:
        """Wake an idle thread, here or in another server process: a job was queued."""
        self.wake()
        self.store.bus.publish("jobs", None)

    def wake(self) -> None:
        """Wake one idle job thread of this process to look for queued work."""
        with self._wake:
            self._wake.notify()

    def cancel(self, model_id: str) -> None:
        """Kill the worker of a job here (its row was deleted or cancelled) and wait for
        it, so that it writes nothing after the caller removes its files."""
        proc = self._running.get(model_id)
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()

    def stop(self) -> None:
        """Kill running workers and queue their jobs again: a clean stop costs no attempt."""
        self._stopping.set()
        with self._wake:
            self._wake.notify_all()
        for proc in list(self._running.values()):
            if proc.poll() is None:
                proc.kill()  # each thread then queues its job again
        self.runner.close()
        for thread in [*self._threads, *([self._reaper] if self._reaper else [])]:
            thread.join(timeout=10)
        self.runner.close()  # any a thread started meanwhile

    def _loop(self) -> None:
        while not self._stopping.is_set():
            try:
                if not self._running:  # a running job's thread does it once it is drawn
                    self.runner.prepare()
                row = self.state.claim_next(self.per_account)
                if row is None:
                    with self._wake:
                        self._wake.wait(POLL_SECONDS)
                    continue
                self._run(row.id)
            except Exception:  # keep the thread alive through a database hiccup
                log.exception("job thread error")
                self._stopping.wait(POLL_SECONDS)

    def _reap(self) -> None:
        """Queue again the jobs of server processes that died while others run on."""
        while not self._stopping.wait(REAP_SECONDS):
            try:
                self.store.bus.hold_liveness()  # lost with its connection: taken again
                requeued, failed = self.state.reap(MAX_ATTEMPTS)
            except Exception:
                log.exception("looking for jobs of stopped server processes")
                continue
            if requeued or failed:
                log.warning(
                    "jobs of a stopped server process: %d queued again, %d failed",
                    len(requeued),
                    len(failed),
                )
                self.wake()

    def _run(self, model_id: str) -> None:
        log_path = self.store.model_dir(model_id) / "worker.log"
        offset = log_path.stat().st_size if log_path.exists() else 0
        started = time.monotonic()
        proc = self.runner.start(model_id)
        self._running[model_id] = proc
        if self._stopping.is_set():  # claimed while stop() was killing the others
            proc.kill()
        self.state.set_pid(model_id, proc.pid)
        log.info("job %s started in process %d", model_id, proc.pid)
        try:
            code = self._wait(model_id, proc)
        finally:
            self._running.pop(model_id, None)
        log.info("job %s: worker ended with code %d", model_id, code)
        try:
            self._record(model_id, time.monotonic() - started)
        except Exception:  # a metric never costs a job
            log.exception("job %s: recording its duration", model_id)
        if self._stopping.is_set():
            self.state.requeue(model_id, count_attempt=False)
            return
        # The child records its own outcome; a row still running means it could not.
        if code != 0:
            reason = crash_reason(code, read_log(log_path, offset), self.cpu_seconds)
        else:
            reason = "worker ended without recording a result; see its worker.log."
        if self.state.fail(model_id, reason, pid=proc.pid):
            remove_outputs(self.store.model_dir(model_id))  # no half model stays
            log.warning("job %s: %s", model_id, reason)
        elif self.state.status(model_id) == FAILED:  # cancelled: what it wrote since goes too
            remove_outputs(self.store.model_dir(model_id))

    def _wait(self, model_id: str, proc: Running) -> int:
        """The worker's exit code. Meanwhile, once the job's model can be drawn (its GLB, or
        its levels of detail, in place: the rest is the other formats and the error) and a
        viewer that follows the job has drawn it (:mod:`miss.server.jobs.turn`), the
        runner gets its next worker ready, not before: a spare warming up beside the job,
        at the job's own priority, had slowed its first seconds (the read, the preview)
        while the browser loaded the viewer, and the model's first frame in a browser on
        the same machine. A worker that has dropped to SCHED_IDLE (its account has more
        jobs waiting: :func:`miss.server.jobs.worker.yield_when_busy`), behind the spare,
        gets it ready at once: another account's job, posted meanwhile, must not pay a
        worker's cold start (seconds)."""
        while proc.poll() is None and not self._stopping.is_set():
            try:
                if self._drawable(model_id) or yielded(proc.pid):
                    self.runner.prepare()
                    break
            except Exception:  # never costs the job its supervision: the loop does it after
                log.exception("job %s: getting the next worker ready", model_id)
                break
            self._stopping.wait(DRAWABLE_POLL_SECONDS)
        return proc.wait()

    def _drawable(self, model_id: str) -> bool:
        """Whether the job's model can be drawn and a viewer that follows the job has drawn
        it (or waited long enough: :func:`turn.held`), or the job has ended."""
        with self.store.session() as s:
            row = s.get(ModelRow, model_id)
        if row is None or row.status != RUNNING:
            return True
        folder = self.store.model_dir(model_id)
        if "lod" in (row.stats or {}):
            drawn = folder / LOD_DIR
        elif "glb" in (row.files or {}):
            drawn = folder / "model.glb"
        else:
            return False
        try:
            since = drawn.stat().st_mtime
        except OSError:  # gone meanwhile (the job failed): nothing to wait for
            return True
        return not turn.held(folder, since)

    def _record(self, model_id: str, seconds: float) -> None:
        if self._stopping.is_set():
            self.on_finished("requeued", seconds)
            return
        with self.store.session() as s:
            row = s.get(ModelRow, model_id)
        self.on_finished(
            row.status if row is not None and row.status != "running" else "failed", seconds
        )
