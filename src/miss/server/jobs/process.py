"""A job's worker process: how it is started (a short bootstrap, spares warmed up ahead,
the server's environment less its secrets) and why it ended when it recorded nothing
(a signal, the CPU limit, an allocation that failed in native code)."""

import contextlib
import os
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

from miss._process import LEAN_ENV
from miss.server.storage.store import Store

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
#: viewers wait: the event loop gets a core whenever it has a request. SCHED_BATCH (a
#: batch thread never preempts on waking) at nice 15 (weight 36 against the server's
#: 1024): nice 10 without SCHED_BATCH had given cached model fetches a p99 of 300 ms or
#: more during jobs. A spare's warm-up runs in a thread of its own at
#: :data:`miss.server.jobs.worker.WARM_UP_NICE`
#: (weight 15), so the next job's warm-up, started beside a running
#: job, takes what that job leaves (issue 39: a small job overlapped by a warm-up had
#: taken twice its time). A job whose account has more jobs queued or running then drops
#: itself to SCHED_IDLE (weight 3; :func:`miss.server.jobs.worker.yield_to_others`), so
#: one account's flood of jobs leaves most of the cores to another account's single job.
#: The order matters: a process may lower its own priority but, without privilege, never
#: raise it back (RLIMIT_NICE), so every worker starts at the highest of the three.
WORKER_NICE = 15

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
    os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
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

    def wait(self) -> int:
        """Wait for the job to end; its exit code."""

    def poll(self) -> int | None:
        """The exit code if the job has ended, else None."""

    def kill(self) -> None:
        """Stop the job at once (SIGKILL for a process)."""


class Runner(Protocol):
    """Where a queued job runs: ``start`` it and hand back its :class:`Running`. The job
    itself (``miss.server.jobs.worker.run_job``) records its outcome in the database; an exit
    code other than 0 without one is a crash the queue records. ``prepare`` (called by a
    queue thread before it waits for work while no job runs, and by a job's thread once
    its model can be drawn) may get workers ready ahead; ``close`` ends them."""

    def start(self, model_id: str) -> Running:
        """Start the job of model ``model_id``; what runs it."""

    def prepare(self) -> None:
        """Get a worker ready ahead of the next job, if this runner can."""

    def close(self) -> None:
        """End the workers made ready ahead."""


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
        env[LEAN_ENV] = "1"  # a worker loads what its jobs need, not the whole API
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
