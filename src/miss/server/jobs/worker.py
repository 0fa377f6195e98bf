"""One job in its own process.

The server starts it through a short bootstrap (``jobs.process._BOOTSTRAP``); by hand it runs as
``python -m miss.server.jobs.worker <model-id> <data-dir> <db-url> <parent-pid>``; the server
passes ``-`` as the URL and writes the real one to the worker's stdin, so that it never
shows in the process list.

Marching cubes and decimation run in native code (VTK, numba) that can crash or run
out of memory; in a child process that costs one job, never the server. The child
reports progress straight to the database, writes its files atomically (the GLB and the
scene the other formats are made from on request: :mod:`miss.server.storage.formats`), and
records its own failure when it can; the parent records the ones it cannot (signals).

Memory: before the job starts, the worker caps its own address space (RLIMIT_AS) at what
it has mapped so far (code, libraries), plus the volume's memory-mapped voxels, plus
``MISS_WORKER_MEMORY_MB`` (read from the environment the server passes on; default the
machine's physical memory, 0 for no cap). An allocation past the cap fails inside the
worker (``MemoryError``, or an abort in native code), and the job fails with "out of
memory", rather than the kernel's out-of-memory killer choosing a victim, perhaps the
server itself.

Limits of one job (issue 39: one account's jobs held the only worker for minutes and
wrote a gigabyte): ``MISS_JOB_CPU_SECONDS`` of CPU time, all threads counted, from the
job's start (RLIMIT_CPU: the kernel ends the worker with SIGXCPU, in native code too,
and the queue records why); ``MISS_JOB_WRITE_MB`` of model files, counted before each
file is written (:class:`DataFolder`), so a job over it writes nothing more, fails, and
what it wrote is removed.

Disk: a full disk while writing the model fails the job with "disk full", removes the
files it had written, and leaves the model's state unfinished: a model is ``done`` only
once every file is in place.
"""

from __future__ import annotations

import contextlib
import ctypes
import hashlib
import json
import math
import os
import resource
import shutil
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from miss.errors import BadParameter, MissError
from miss.export import FORMATS, WRITERS
from miss.export.tiles import etag
from miss.pipeline import PREVIEW, JobResult, execute
from miss.scene import Scene
from miss.server.core.settings import Settings
from miss.server.jobs import turn
from miss.server.jobs.state import JobState
from miss.server.storage import chunked, formats
from miss.server.storage.db import VolumeRow
from miss.server.storage.store import (
    LOD_DIR,
    PART,
    PREVIEW_FILE,
    Store,
    is_disk_full,
    remove_outputs,
    write_atomic,
)
from miss.server.volumes import labelmaps
from miss.spec import JobSpec, Loaded
from miss.types import Volume

#: Seconds between progress writes within one stage: enough for a live bar, light on the DB.
PROGRESS_INTERVAL = 0.3
#: Memory a job may use, MB, beyond the worker's code and the volume's mapped voxels.
MEMORY_ENV = "MISS_WORKER_MEMORY_MB"
#: Triangles above which a model also gets levels of detail.
LOD_ENV = "MISS_LOD_TRIANGLES"
IN_MEMORY_ENV = "MISS_IN_MEMORY_MAX_MB"
CPU_ENV = "MISS_JOB_CPU_SECONDS"
WRITE_ENV = "MISS_JOB_WRITE_MB"
#: Seconds of CPU past the limit before the kernel's SIGKILL, should SIGXCPU be caught.
CPU_GRACE = 5
OUT_OF_MEMORY = "out of memory; choose a larger sample rate or fewer slices."


class WriteLimit(MissError):
    """A job about to write more model files than ``MISS_JOB_WRITE_MB`` allows."""


def over_write_limit(limit: int) -> str:
    """Why a job over its bytes-written limit (``limit`` bytes) failed, and what to do."""
    return (
        f"this job would write more than {limit / 2**20:g} MB of model files, the limit of one "
        f"job ({WRITE_ENV}); choose fewer labels or levels, a larger sample rate or more "
        "decimation, or ask an administrator to raise the limit."
    )


class Stop(Exception):
    """The job was deleted or taken back by the server, or the server died: stop quietly."""


def die_with_parent(parent: int) -> None:
    """Ask Linux to kill this process when the server dies, so no orphan finishes a job
    that the restarted server has already queued again."""
    # Not Linux: no prctl; the progress callback still checks the parent.
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != parent:  # the parent died before prctl took effect
        raise Stop


class Reporter:
    """The pipeline's progress callback: throttled writes of (stage, fraction) to the row."""

    def __init__(self, state: JobState, model_id: str, parent: int) -> None:
        self.state, self.model_id, self.parent = state, model_id, parent
        self.stage, self.last = "", 0.0

    def __call__(self, stage: str, fraction: float) -> None:
        """Write (stage, fraction) to the row at most once every ``PROGRESS_INTERVAL`` seconds per
        stage; raises Stop when the server went away or the job is no longer running."""
        if os.getppid() != self.parent:
            raise Stop
        now = time.monotonic()
        if stage == self.stage and now - self.last < PROGRESS_INTERVAL:
            return
        self.stage, self.last = stage, now
        if not self.state.set_progress(self.model_id, stage, fraction):
            raise Stop


def _setting(env: Mapping[str, str], name: str, fix: str) -> Settings:
    """The settings with only ``name`` read from ``env`` (by :class:`Settings`); a bad
    value raises ``BadParameter`` saying to set it to ``fix``."""
    try:
        return Settings.from_env({name: env.get(name, "")})
    except ValueError as exc:
        raise BadParameter(
            f"{str(exc).rstrip('.')}; set {name} on the server to {fix} and restart it."
        ) from None


def memory_cap(env: Mapping[str, str]) -> int:
    """Bytes a job may allocate (``MISS_WORKER_MEMORY_MB`` in ``env``). Raises
    ``BadParameter`` for a value that is not a number of MB."""
    return _setting(env, MEMORY_ENV, "a number (0 for no cap)").worker_memory_bytes


def cpu_seconds(env: Mapping[str, str]) -> float:
    """CPU seconds a job may use (``MISS_JOB_CPU_SECONDS`` in ``env``); 0: no limit."""
    return _setting(env, CPU_ENV, "a number of seconds (0: no limit)").job_cpu_seconds


def write_bytes(env: Mapping[str, str]) -> int | None:
    """Bytes of model files a job may write (``MISS_JOB_WRITE_MB`` in ``env``); None: no
    limit."""
    return _setting(env, WRITE_ENV, "a number of MB (0: no limit)").job_write_bytes or None


def limit_cpu(seconds: float) -> None:
    """Have the kernel end this process (SIGXCPU) once it has used ``seconds`` of CPU more
    than now: a spare's warm-up is not the job's. No core file: the data folder is the
    working directory. 0 leaves it alone."""
    if seconds <= 0:
        return
    usage = resource.getrusage(resource.RUSAGE_SELF)
    soft = math.ceil(usage.ru_utime + usage.ru_stime + seconds)
    resource.setrlimit(resource.RLIMIT_CORE, (0, resource.getrlimit(resource.RLIMIT_CORE)[1]))
    hard = resource.getrlimit(resource.RLIMIT_CPU)[1]
    new_hard = soft + CPU_GRACE
    if hard != resource.RLIM_INFINITY:
        new_hard = min(new_hard, hard)
    resource.setrlimit(resource.RLIMIT_CPU, (min(soft, new_hard), new_hard))


#: Seconds between a job's looks at its account's queue (one count query each).
BUSY_POLL_SECONDS = 1.0


def yield_when_busy(state: JobState, model_id: str, account: str | None) -> None:
    """Drop this worker to SCHED_IDLE now if ``account`` has more jobs queued or running,
    else as soon as it has (a thread looks every :data:`BUSY_POLL_SECONDS`): a flood's
    first job is claimed before its second is posted."""
    others = state.others_waiting(model_id, account)
    if others:
        yield_to_others(others)
        return

    def watch() -> None:
        while True:
            time.sleep(BUSY_POLL_SECONDS)
            with contextlib.suppress(Exception):  # a database hiccup: look again
                others = state.others_waiting(model_id, account)
                if others:
                    yield_to_others(others)
                    return

    threading.Thread(target=watch, name="miss-busy", daemon=True).start()


def yield_to_others(others: int) -> None:
    """Drop every thread of this worker to SCHED_IDLE: its account has ``others`` more jobs
    queued or running, so another account's job (at the workers' SCHED_BATCH) gets five
    times its share of a contended core. Threads started earlier (numba's and VTK's pools,
    made by the warm-up) are moved one by one; later ones inherit it from the thread that
    starts them. For good: without privilege a process cannot raise its priority again."""
    moved = 0
    with contextlib.suppress(OSError):  # no /proc: not Linux, the policy stays
        for task in os.listdir("/proc/self/task"):
            with contextlib.suppress(OSError, AttributeError):  # a thread that just ended
                os.sched_setscheduler(int(task), os.SCHED_IDLE, os.sched_param(0))
                moved += 1
    print(
        f"this account has {others} more job(s) queued or running: {moved} thread(s) of "
        "this worker run at SCHED_IDLE, behind other accounts' jobs",
        file=sys.stderr,
        flush=True,
    )


def mapped_bytes() -> int | None:
    """The address space this process uses now (VmSize), None where /proc is missing."""
    try:
        status = Path("/proc/self/status").read_text()
    except OSError:
        return None
    line = next((x for x in status.splitlines() if x.startswith("VmSize:")), None)
    return int(line.split()[1]) * 1024 if line else None


def in_memory_max(env: Mapping[str, str]) -> int:
    """``MISS_IN_MEMORY_MAX_MB`` in ``env`` as bytes (``Store.in_memory_max``)."""
    return _setting(env, IN_MEMORY_ENV, "a number of MB").in_memory_max_bytes


def voxel_bytes(folder: Path) -> int:
    """What the voxels of a volume's folder (volume and label map) take decompressed: the
    job holds them whole (``Store.open_volume``), or its region of a lazy one, at most as
    much; .npy files not migrated yet are memory-mapped, their size in the address space."""
    zarrs = sum(chunked.nbytes(p) for p in folder.glob("*.zarr"))
    return zarrs + sum(p.stat().st_size for p in folder.glob("*.npy"))


def limit_memory(store: Store, volume_id: str, cap: int) -> None:
    """Cap the address space: mapped now + the volume's voxels (``voxel_bytes``) +
    ``cap``; 0 leaves it alone."""
    now = mapped_bytes()
    if cap <= 0 or now is None:
        return
    files = voxel_bytes(store.volume_dir(volume_id))
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    limit = now + files + cap
    if hard != resource.RLIM_INFINITY:
        limit = min(limit, hard)
    if soft == resource.RLIM_INFINITY or limit < soft:
        resource.setrlimit(resource.RLIMIT_AS, (limit, hard))


def lod_budget(env: Mapping[str, str]) -> int | None:
    """Triangles above which a model gets levels of detail (``MISS_LOD_TRIANGLES``);
    None when it is 0 (never)."""
    return _setting(env, LOD_ENV, "a number of triangles (0: never)").lod_triangles or None


def write_tree_atomic(folder: Path, files: Mapping[str, bytes]) -> None:
    """Write ``{relative name: bytes}`` into a hidden folder beside ``folder``, then rename
    it into place (an older one is dropped first): nobody sees half a tileset."""
    tmp = folder.with_name(f".{folder.name}.{os.getpid()}{PART}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        for name, data in files.items():
            path = tmp / name
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
        if folder.exists():
            old = folder.with_name(f".{folder.name}.old{PART}")
            os.replace(folder, old)
            shutil.rmtree(old, ignore_errors=True)
        os.replace(tmp, folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


@dataclass(frozen=True, eq=False)
class StoredVolume:
    """A job's source in the server: an uploaded volume of the data folder, with the label
    map laid over it when the job asks for labels."""

    store: Store
    volume_id: str

    def load(self, labels: bool) -> Loaded:
        """The stored volume, with its label map and label table when ``labels`` and it has one."""
        row = self.store.get_volume(self.volume_id)
        stored = labelmaps.load(self.store, self.volume_id) if labels else None
        label_map, table = stored if stored else (None, None)
        volume = self.store.open_volume(self.volume_id)
        return Loaded(volume, label_map, table, row.name, _provenance(row))


def _provenance(row: VolumeRow) -> dict[str, str]:
    """What a model file says of its volume: the hash of the (de-identified) voxels, never
    a patient name, ID or original UID."""
    return {
        "source": row.slug,
        "source_sha256": str(row.info.get("source_sha256", "")),
        "modality": str(row.info.get("modality", "")),
        "deidentified": "yes" if row.info.get("deidentification") else "no patient data",
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
    }


@dataclass
class DataFolder:
    """A job's files in the server: ``models/<id>/model.<fmt>`` (and ``preview.glb``), each
    written atomically and recorded in the running job's row as soon as it is in place, so
    the viewer draws the preview and then the model while the rest is written; delivers
    {fmt: {bytes, etag, mime}} in the formats' order. A model over ``lod_triangles`` also
    gets its levels of detail in ``models/<id>/lod/`` first (``lod`` says what they are),
    recorded at once: the viewer draws them rather than the GLB."""

    folder: Path
    state: JobState
    model_id: str
    wants_preview: bool = True
    lod_triangles: int | None = None
    #: Bytes of files the job may write here (``MISS_JOB_WRITE_MB``); None: no limit.
    write_limit: int | None = None
    written: int = 0
    lod: dict[str, Any] | None = None
    preview: dict[str, Any] | None = None
    files: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: Seconds from ``started`` (the job's start) until the model's GLB was in place.
    started: float = field(default_factory=time.perf_counter)
    ready_seconds: float | None = None
    #: Whether the scene for the other formats is stored (:meth:`keep_scene`).
    kept: bool = False
    #: :meth:`count` is called from the pipeline's writing and keeping threads.
    counting: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def count(self, size: int) -> None:
        """Count ``size`` bytes about to be written; raises :class:`WriteLimit` (before
        they are) when they would take the job over its limit."""
        with self.counting:
            if self.write_limit is not None and self.written + size > self.write_limit:
                raise WriteLimit(over_write_limit(self.write_limit))
            self.written += size

    def put(self, fmt: str, data: bytes) -> None:
        """Write one format's bytes (or the preview) into the model's folder and record them on
        the row at once; raises WriteLimit over the job's write limit, Stop when the job is gone."""
        self.count(len(data))
        self.folder.mkdir(parents=True, exist_ok=True)
        meta = {"bytes": len(data), "etag": hashlib.sha256(data).hexdigest()[:32]}
        if fmt == PREVIEW:
            write_atomic(self.folder / PREVIEW_FILE, data)
            self.preview = meta
            if not self.state.set_preview(self.model_id, meta):
                raise Stop
            return
        write_atomic(self.folder / f"model.{fmt}", data)
        self.files[fmt] = meta | {"mime": WRITERS[fmt].mime}
        if fmt == "glb" and self.ready_seconds is None:
            self.ready_seconds = time.perf_counter() - self.started
        if not self.state.set_files(self.model_id, self.files):
            raise Stop

    def wait_for_viewer(self) -> float:
        """Hold back the rest of the job while a viewer that follows it draws the model
        (:mod:`miss.server.jobs.turn`); the seconds waited."""
        return turn.wait_turn(self.folder, time.time())

    def put_lod(self, files: Mapping[str, bytes]) -> None:
        """Write the levels of detail into ``lod/`` and record them on the row; raises WriteLimit
        over the job's write limit, Stop when the job is gone."""
        self.count(sum(map(len, files.values())))
        write_tree_atomic(self.folder / LOD_DIR, files)
        tiles = sum(1 for name in files if name.endswith(".glb"))
        self.lod = {"etag": etag(files), "bytes": sum(map(len, files.values())), "tiles": tiles}
        if not self.state.set_lod(self.model_id, self.lod, self.preview):
            raise Stop

    def deliver(self, result: JobResult) -> dict[str, Any]:
        """The files written, ``{fmt: {bytes, etag, mime}}``, in the job's formats' order."""
        return {fmt: self.files[fmt] for fmt in result.artifacts}

    def keep_scene(self, scene: Scene, title: str | None, metadata: dict[str, str]) -> None:
        """Store the scene the job encoded (:mod:`miss.server.storage.formats`), from which
        the other formats are made on their first download (the pipeline calls it on a
        thread of its own while the files are written)."""
        data = formats.scene_bytes(scene, title, metadata)
        self.count(len(data))
        self.folder.mkdir(parents=True, exist_ok=True)
        write_atomic(self.folder / formats.MESH_FILE, data)
        self.kept = True

    def listing(self, result: JobResult) -> dict[str, Any]:
        """Every format's ``files`` entry in the formats' order, those not made yet without
        bytes nor ETag (the scene kept first, if the pipeline did not)."""
        if not self.kept:
            self.keep_scene(result.scene, result.title, result.metadata)
        made = {fmt: meta | {"on_request": False} for fmt, meta in self.files.items()}
        listed = formats.entries(result.scene) | made
        return {fmt: listed[fmt] for fmt in FORMATS if fmt in listed}


def summarize(
    result: JobResult, ready_seconds: float | None = None, lod: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The stats the API shows: triangles, vertices, seconds per stage, bytes, error in mm,
    parts, the bounding box in patient mm (the rooms check pins against it), provenance,
    ``ready_seconds``: how long the job took until the model could be drawn, and ``lod``:
    the levels of detail's etag, bytes and tiles when it has them."""
    stats = result.stats()
    if ready_seconds is not None:
        stats["ready_seconds"] = ready_seconds
    if lod is not None:
        stats["lod"] = lod
    stats["max_error_mm"] = result.report.max_error_mm
    stats["mean_error_mm"] = result.report.mean_error_mm
    if result.scene.n_vertices:
        stats["bounds_mm"] = result.scene.bounds().tolist()
    stats["provenance"] = result.metadata
    return json.loads(json.dumps(stats, default=float))


#: The server sends meshopt-compressed glTF: about 4 bytes a triangle to the viewer.
EXPORT_OPTIONS = {"glb": {"compress": True}}


def run_job(store: Store, model_id: str, parent: int) -> None:
    """Compute one model and record it as done (or raise)."""
    started, cpu = time.perf_counter(), time.process_time()
    row = store.get_model(model_id)
    state = JobState(store)
    yield_when_busy(state, model_id, row.submitted_by)
    limit_memory(store, row.volume_id, memory_cap(os.environ))
    limit_cpu(cpu_seconds(os.environ))
    reporter = Reporter(state, model_id, parent)
    source = StoredVolume(store, row.volume_id)
    spec = JobSpec.from_dict({**row.spec, "formats": formats.KEPT}, source)
    folder = DataFolder(
        store.model_dir(model_id), state, model_id, lod_triangles=lod_budget(os.environ),
        write_limit=write_bytes(os.environ), started=started,
    )  # fmt: skip
    turn.forget(folder.folder)
    result, _ = execute(spec, folder, reporter, export_options=EXPORT_OPTIONS)
    reporter("store", 1.0)
    files = folder.listing(result)  # the scene was kept while the files were written
    print(  # what an administrator sizes MISS_JOB_CPU_SECONDS and MISS_JOB_WRITE_MB by
        f"job {model_id}: {time.process_time() - cpu:.1f} s of CPU, "
        f"{folder.written / 2**20:.1f} MB of model files written",
        file=sys.stderr,
        flush=True,
    )
    if not state.finish(model_id, summarize(result, folder.ready_seconds, folder.lod), files):
        raise Stop


def failure_reason(exc: Exception, model_id: str, data_dir: Path) -> str:
    """What to tell the physician (and the administrator) about a failed job."""
    if isinstance(exc, MissError):
        return str(exc)
    if isinstance(exc, MemoryError):
        return OUT_OF_MEMORY
    if is_disk_full(exc):
        return f"disk full: free space in {data_dir}, then submit the same parameters again."
    return (
        f"internal error ({type(exc).__name__}: {exc}); "
        f"see models/{model_id}/worker.log in the data folder."
    )


def main(argv: list[str]) -> int:
    """Exit 0 when the outcome (done or a failure reason) is in the database.

    ``-`` as the model id makes a spare: it loads everything a job needs first
    (:func:`warm_up`), then reads its model id from stdin and writes its output to that
    model's ``worker.log``; an empty line (the server has no job for it) ends it."""
    model_id, data_dir, db_url, parent = argv[0], Path(argv[1]), argv[2], int(argv[3])
    if db_url == "-":  # from the server: on stdin, out of sight of ps
        db_url = sys.stdin.readline().strip()
    store = Store(data_dir, db_url, in_memory_max(os.environ))
    try:
        if model_id == "-":
            start = time.monotonic()
            warming = warm_up_behind(WARM_UP_STEPS)
            model_id = sys.stdin.readline().strip()
            # A job that came early: the step under way ends (its imports, not twice); the
            # job does the rest itself at its own priority, not waiting behind WARM_UP_NICE.
            warming.stop.set()
            warming.join()
            warm = warming.seconds
            if not model_id:
                return 3
            log_to(store.model_dir(model_id) / "worker.log")
            waited = time.monotonic() - start - warm
            steps = len(WARM_UP_STEPS)
            early = f"{warming.done} of {steps} steps " if warming.done < steps else ""
            print(
                f"spare worker {os.getpid()} (warmed up {early}in {warm:.2f} s, then waited "
                f"{waited:.1f} s) takes job {model_id}",
                file=sys.stderr,
                flush=True,
            )
        return attempt(store, model_id, parent)
    finally:
        store.close()


#: The nice value of a spare worker's warm-up thread: below the job's own
#: (:data:`miss.server.jobs.process.WORKER_NICE`), so the next job's warm-up, started while
#: a job runs, takes only what that job leaves.
WARM_UP_NICE = 19


class _WarmUp(threading.Thread):
    """Runs ``steps`` in turn at :data:`WARM_UP_NICE` (Linux: a thread's nice value is its
    own) until :attr:`stop` is set; keeps how many ran in :attr:`done` and how long they
    took, in seconds, in :attr:`seconds`."""

    def __init__(self, steps: Sequence[Callable[[], None]]) -> None:
        super().__init__(name="miss-warm-up", daemon=True)
        self.steps = steps
        self.stop = threading.Event()
        self.done = 0
        self.seconds = 0.0

    def run(self) -> None:
        start = time.monotonic()
        with contextlib.suppress(OSError):  # not allowed (or not Linux): the job's priority
            os.setpriority(
                os.PRIO_PROCESS, 0, max(os.getpriority(os.PRIO_PROCESS, 0), WARM_UP_NICE)
            )
        try:
            for step in self.steps:
                if self.stop.is_set():
                    break
                step()
                self.done += 1
        finally:
            self.seconds = time.monotonic() - start


def warm_up_behind(steps: Sequence[Callable[[], None]]) -> _WarmUp:
    """Start ``steps`` (:data:`WARM_UP_STEPS`) in a thread at :data:`WARM_UP_NICE` and
    return it; the caller waits for its job meanwhile, then sets its ``stop`` and joins
    it before running the job: a job that comes early waits for one step, not all."""
    thread = _WarmUp(steps)
    thread.start()
    return thread


def _phantom() -> Volume:
    from miss.demo import phantom

    return phantom(40, spacing=5.0)


def _warm_read() -> None:
    """Reading is the first thing a job does, before its preview: zarr's import alone
    took 0.39-0.47 s of a first pixel at 1.2-1.7 s. Best effort: a temporary folder that
    cannot be written (full, read-only) leaves the read to load on the first job, not a
    spare that dies."""
    import tempfile

    head = _phantom()
    with contextlib.suppress(OSError, MissError), tempfile.TemporaryDirectory() as tmp:
        stored = Path(tmp) / "voxels"
        chunked.write_array(stored, head.data, {"affine": head.affine.tolist()})
        chunked.read(stored, in_memory_max=head.data.nbytes)


def _warm_decimate() -> None:
    from miss.decimate.schroeder import warm_up as warm_schroeder

    warm_schroeder()


def _warm_surface() -> None:
    """What a job writes itself (the other formats are made on request, by the server)."""
    from miss.pipeline import run

    head = _phantom()
    done = run(head, JobSpec.of(level=300, formats=formats.KEPT), export_options=EXPORT_OPTIONS)
    formats.scene_bytes(done.scene, done.title, done.metadata)


def _warm_labels() -> None:
    import numpy as np

    from miss.pipeline import run

    head = _phantom()
    labels = np.asfortranarray((head.data > -500).astype(np.uint8) + (head.data > 300))
    spec = JobSpec.of(labels="all", formats=formats.KEPT)
    run(Volume(labels, head.affine), spec, export_options=EXPORT_OPTIONS)


#: What a spare worker loads and runs once, on a small phantom, before its job comes, in
#: the order a job needs them (reading a stored volume, the numba kernels, VTK and
#: meshoptimizer with the GLB writer and the kept scene, the label-map path), so that its
#: job starts computing at once: a few seconds of imports and first calls.
WARM_UP_STEPS: tuple[Callable[[], None], ...] = (
    _warm_read,
    _warm_decimate,
    _warm_surface,
    _warm_labels,
)


def warm_up() -> None:
    """Every step of :data:`WARM_UP_STEPS`, here and now."""
    for step in WARM_UP_STEPS:
        step()


def log_to(path: Path) -> None:
    """Send this process's stdout and stderr (native code's too) to the end of ``path``."""
    sys.stdout.flush()
    sys.stderr.flush()
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)


def attempt(store: Store, model_id: str, parent: int) -> int:
    """Run the job; record a failure with its reason. Returns the exit code."""
    try:
        die_with_parent(parent)
        run_job(store, model_id, parent)
        return 0
    except Stop:
        return 3
    except Exception as exc:
        expected = isinstance(exc, MissError | MemoryError) or is_disk_full(exc)
        if not expected:
            traceback.print_exc()
        reason = failure_reason(exc, model_id, store.data_dir)
    # Outside the except block: the traceback, and the arrays its frames hold, are gone,
    # so recording an out-of-memory failure has its memory back.
    remove_outputs(store.model_dir(model_id))
    JobState(store).fail(model_id, reason)
    return 0 if expected else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
