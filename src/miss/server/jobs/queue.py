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

import contextlib
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

from miss.server.jobs import turn
from miss.server.jobs.state import JobState
from miss.server.storage.db import RUNNING, ModelRow
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


#: What native code and Python print when an allocation fails: the worker hit its memory
#: cap (``MISS_WORKER_MEMORY_MB``) where no ``MemoryError`` could be caught.
_OUT_OF_MEMORY_SIGNS = (
    "MemoryError",
    "std::bad_alloc",
    "Unable to allocate",
    "Cannot allocate memory",
    "Memory allocation",
    "out of memory",
)
#: How much of the end of a worker's log is read for those signs, bytes.
_LOG_TAIL = 64 * 1024


def over_cpu(seconds: float) -> str:
    """Why a job over its CPU limit (``seconds``) failed, and what to do."""
    return (
        f"this job used more than {seconds:g} s of CPU, the limit of one job "
        "(MISS_JOB_CPU_SECONDS); choose a larger sample rate, fewer levels or labels or less "
        "smoothing, or ask an administrator to raise the limit."
    )


def crash_reason(returncode: int, log_tail: str = "", cpu_seconds: float = 0.0) -> str:
    """Why a worker ended without recording an outcome, in words; ``log_tail`` is what it
    wrote to its worker.log during this run, ``cpu_seconds`` the job's CPU limit."""
    if returncode == -signal.SIGXCPU and cpu_seconds > 0:
        return over_cpu(cpu_seconds)
    if returncode < 0:
        sig = -returncode
        name = signal.Signals(sig).name if sig in signal.Signals._value2member_map_ else "?"
        ended = f"signal {sig} ({name})"
    else:
        ended = f"code {returncode}"
    if any(sign in log_tail for sign in _OUT_OF_MEMORY_SIGNS):
        return (
            f"out of memory (the worker ended with {ended}); "
            "choose a larger sample rate or fewer slices."
        )
    if returncode < 0:
        hint = (
            " (most likely out of memory; choose a larger sample rate or fewer slices)"
            if sig == signal.SIGKILL
            else ""
        )
        return f"worker crashed with {ended}{hint}."
    return f"worker exited with {ended} without a result; see its worker.log."


def read_log(path: Path, offset: int) -> str:
    """The end of what was written to ``path`` after ``offset`` ("" if unreadable)."""
    try:
        with open(path, "rb") as f:
            size = f.seek(0, os.SEEK_END)
            f.seek(max(offset, size - _LOG_TAIL))
            return f.read().decode("utf-8", "replace")
    except OSError:
        return ""


#: Workers run at a lower priority than the server, so that a long conversion never makes
#: viewers wait: the event loop gets a core whenever it has a request. They also ask for
#: SCHED_IDLE (Linux, no privilege needed): nice alone still gave a worker's threads a
#: share of the server's core, and cached model fetches a p99 of 300 ms or more during
#: jobs; with it, about 15 ms. A conversion still gets every core nobody else wants.
WORKER_NICE = 10

#: The worker's first lines, run before it imports VTK and numba (seconds): Linux is asked
#: to kill it when the server dies (PR_SET_PDEATHSIG), so a server killed meanwhile never
#: leaves a worker behind that finishes a job the restarted server has queued again.
_BOOTSTRAP = f"""\
import ctypes, os, sys
try:
    ctypes.CDLL(None).prctl(1, 9)
except (OSError, AttributeError):
    pass
if os.getppid() != int(sys.argv[4]):
    sys.exit(3)
os.nice({WORKER_NICE})
try:
    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
except (AttributeError, OSError):
    pass
from miss.server.jobs.worker import main
sys.exit(main(sys.argv[1:]))
"""


#: Where spare workers write until they have a job (then they write to its worker.log).
SPARES_LOG = "spare-workers.log"

#: Environment variables a worker does not need and must not see.
WORKER_HIDDEN_ENV = frozenset({"MISS_ADMIN_PASSWORD", "MISS_DATABASE_URL"})


class Running(Protocol):
    """A job under way somewhere: what the queue needs to wait for it or stop it."""

    pid: int

    def wait(self) -> int: ...

    def poll(self) -> int | None: ...

    def kill(self) -> None: ...


class Runner(Protocol):
    """Where a queued job runs: ``start`` it and hand back its :class:`Running`. The job
    itself (``miss.server.jobs.worker.run_job``) records its outcome in the database; an exit
    code other than 0 without one is a crash the queue records. ``prepare`` (called by a
    queue thread before it waits for work while no job runs, and by a job's thread once
    its model can be drawn) may get workers ready ahead; ``close`` ends them."""

    def start(self, model_id: str) -> Running: ...

    def prepare(self) -> None: ...

    def close(self) -> None: ...


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
        with self._wake:
            self._wake.notify()

    def cancel(self, model_id: str) -> None:
        """Kill the worker of a job (its row was deleted)."""
        proc = self._running.get(model_id)
        if proc is not None and proc.poll() is None:
            proc.kill()

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
        if self.state.fail(model_id, reason):
            remove_outputs(self.store.model_dir(model_id))  # no half model stays
            log.warning("job %s: %s", model_id, reason)

    def _wait(self, model_id: str, proc: Running) -> int:
        """The worker's exit code. Meanwhile, once the job's model can be drawn (its GLB, or
        its levels of detail, in place: the rest is the other formats and the error) and a
        viewer that follows the job has drawn it (:mod:`miss.server.jobs.turn`), the
        runner gets its next worker ready, not before: a spare warming up beside the job,
        at the job's own priority, had slowed its first seconds (the read, the preview)
        while the browser loaded the viewer, and the model's first frame in a browser on
        the same machine."""
        while proc.poll() is None and not self._stopping.is_set():
            try:
                if self._drawable(model_id):
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


@dataclass(eq=False)
class WorkerProcess:
    """Each job in a child process of its own (``python -m miss.server.jobs.worker``): native
    code that crashes or runs out of memory costs one job, never the server.

    ``spares`` processes are started ahead: each imports and warms up everything a job
    uses (``worker.warm_up``), then waits on its stdin for a model id, so a job starts
    computing at once instead of seconds later. The one that replaces a spare given a job
    is started once that job's model can be drawn (:meth:`JobQueue._wait`), not beside
    its first seconds. Still one job a process, with the same
    memory cap and the same log. Spares are started by the queue's own threads, which live
    as long as the server: Linux sends a worker's death signal when the *thread* that
    started it ends (``PR_SET_PDEATHSIG``).
    """

    store: Store
    spares: int = 0
    #: Set in the workers' environment beside the server's own (the job limits).
    env: dict[str, str] = field(default_factory=dict)
    _ready: list[subprocess.Popen[bytes]] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _closed: bool = False

    def start(self, model_id: str) -> subprocess.Popen[bytes]:
        """A spare given ``model_id``, or a new worker for it; its output goes to
        ``models/<id>/worker.log``."""
        folder = self.store.model_dir(model_id)
        folder.mkdir(parents=True, exist_ok=True)
        proc = self._spare_for(model_id)
        if proc is None:
            proc = self._spawn(model_id, folder / "worker.log")
        return proc

    def prepare(self) -> None:
        """Start spares until ``spares`` are waiting (dead ones are dropped)."""
        with self._lock:
            self._ready = [p for p in self._ready if p.poll() is None]
            while not self._closed and len(self._ready) < self.spares:
                self._ready.append(self._spawn("-", self.store.data_dir / SPARES_LOG))

    def close(self) -> None:
        """End the waiting spares: they hold nothing but loaded code."""
        with self._lock:
            self._closed = True
            ready, self._ready = self._ready, []
        for proc in ready:
            proc.kill()
            proc.wait()
            with contextlib.suppress(OSError):
                assert proc.stdin is not None
                proc.stdin.close()

    def _spare_for(self, model_id: str) -> subprocess.Popen[bytes] | None:
        while True:
            with self._lock:
                if not self._ready:
                    return None
                proc = self._ready.pop(0)
            assert proc.stdin is not None
            try:
                proc.stdin.write(f"{model_id}\n".encode())
                proc.stdin.close()
                return proc
            except (BrokenPipeError, ValueError):  # it died while waiting: the next one
                proc.wait()

    def _spawn(self, model_id: str, log_path: Path) -> subprocess.Popen[bytes]:
        # The database URL (it may hold a password) goes through stdin, not the command
        # line, which every local user can read in ps; the admin password stays behind.
        cmd = [sys.executable, "-c", _BOOTSTRAP, model_id, str(self.store.data_dir), "-"]
        cmd.append(str(os.getpid()))
        env = {k: v for k, v in os.environ.items() if k not in WORKER_HIDDEN_ENV} | self.env
        with open(log_path, "ab") as log_file:
            # A session of its own: a Ctrl-C in the server's terminal reaches the server,
            # which stops the workers itself and queues their jobs again.
            proc = subprocess.Popen(
                cmd,
                stdin=subprocess.PIPE,
                stdout=log_file,
                stderr=log_file,
                cwd=self.store.data_dir,
                env=env,
                start_new_session=True,
            )
        assert proc.stdin is not None
        with contextlib.suppress(BrokenPipeError):  # a worker that died at once
            proc.stdin.write(self.store.database_url.encode() + b"\n")
            if model_id == "-":
                proc.stdin.flush()  # a spare reads its model id later
            else:
                proc.stdin.close()
        return proc
