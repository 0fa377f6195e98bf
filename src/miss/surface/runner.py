"""Where block tasks run: threads in this process, a local Dask cluster, or a remote one.

- ``MISS_DASK_SCHEDULER=tcp://host:8786`` (or ``--scheduler``) sends every block to that
  cluster; its workers must reach the data by the same path (a ``zarr.Array`` travels as a
  reference to its folder; an in-memory array is scattered to the workers once).
- Otherwise volumes of at least :data:`CLUSTER_VOXELS` voxels start a ``LocalCluster``
  (one single-threaded worker process per core); smaller ones run on a thread pool, where
  the cluster's start (about 3 s here) and the meshes' trips cost more than it saves.

Results are handed to the caller as they arrive (from threads, in the items' order), so it
can weld them and drop each one; a Dask worker on the caller's machine leaves them in
shared memory for it (:func:`_left`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from functools import partial
from typing import Any

from miss.errors import MissError

#: Volumes with at least this many voxels (after sampling) run on a local Dask cluster when
#: no scheduler is given; smaller ones on threads. Measured here (2 cores,
#: benchmarks/results/scale*.md): threads are faster at every size tried, 1.15 s against
#: 1.9-3.6 s on two workers at 157 M voxels, 7.4 s against 12.5-13.2 s at 1.26 G (a
#: cluster's start, ~3 s, not counted), as the job's process receives and welds every
#: block's mesh either way. The cluster is kept for the volumes past 1 G voxels for memory:
#: a job that decimates its blocks where they were made holds the full-resolution blocks
#: until the bound is known, in the job's process on threads (the surface of 1.26 G voxels took
#: 1.9 GB there), spread over the workers on a cluster (829 MB at most in any process). Re-measure with more cores.
CLUSTER_VOXELS = 1_000_000_000

SCHEDULER_ENV = "MISS_DASK_SCHEDULER"

#: Dask's nannies start workers with MALLOC_TRIM_THRESHOLD_=65536, which hands every
#: large array back to the system when freed: a block's surface took 1.6x as long in such a
#: worker as in this process (measured here: 4.0 s against 2.6 s for the same 125 blocks).
#: Unset for the local cluster; start remote workers with this too (README).
NANNY_ENVIRON = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}

#: Dask settings for MISS's clusters (the local one is started with them; give a remote
#: scheduler and its workers the same, README): :data:`NANNY_ENVIRON`, and no queuing of
#: root tasks at the scheduler (``worker-saturation``: its default 1.1 hands a worker its
#: next block only after the last one is reported, a round trip per block; the blocks are
#: independent and about equal, so they all go out at once and work stealing evens them).
CLUSTER_CONFIG = {**NANNY_ENVIRON, "distributed.scheduler.worker-saturation": float("inf")}

#: Imported by every worker of the local cluster as it starts (``--preload`` for remote
#: ones): VTK, numpy and zarr load before the first block, not inside the job's time.
PRELOAD = ["miss.surface.blockwise", "zarr"]


class SchedulerUnreachable(MissError, ConnectionError):
    """The Dask scheduler named by ``--scheduler`` or ``MISS_DASK_SCHEDULER`` did not answer."""


class BlockTaskFailed(MissError, RuntimeError):
    """A block task failed on the cluster (a worker died too often, or the task raised)."""


def scheduler_address(given: str | None = None) -> str | None:
    """The scheduler to use: ``given``, else ``MISS_DASK_SCHEDULER``, else None (local)."""
    return given or os.environ.get(SCHEDULER_ENV) or None


def run_blocks(
    task: Callable[..., Any],
    shared: Any,
    items: Sequence[Any],
    *,
    scheduler: str | None = None,
    cluster: bool = False,
    progress: Callable[[int, int], None] | None = None,
    then: Then | None = None,
) -> Iterator[Any]:
    """Yield ``task(shared, item)`` for every item: in the order they finish on Dask, in
    the items' order on threads (so that a job made there is the same every run).

    ``scheduler`` is a Dask address (``tcp://host:8786``); without one, ``cluster`` starts
    a LocalCluster sized to the machine, else a thread pool runs the tasks.
    ``progress(done, total)`` is called after each result.

    With ``then = (look, decide)``, the tasks' results stay where they were made (a
    worker's memory); ``decide([look(result), ...])`` (the looks in item order, small)
    returns a function ``finish``, and ``finish(result)`` is yielded for each item, run
    where the result is. Progress counts both waves.
    """
    total = len(items) * (2 if then else 1)
    if scheduler is None and not cluster:
        runs = _on_threads(task, shared, items, then)
    else:
        runs = _on_dask(task, shared, items, scheduler, then)
    for done, result in enumerate(runs, start=1):
        if progress is not None:
            progress(done, total)
        if result is not _FIRST_WAVE:
            yield result


#: (look, decide): see :func:`run_blocks`.
Then = tuple[Callable[[Any], Any], Callable[[list[Any]], Callable[[Any], Any]]]
#: What the runners hand back for each result of a first wave (counted, not yielded).
_FIRST_WAVE = object()


def _on_threads(
    task: Callable[..., Any], shared: Any, items: Sequence[Any], then: Then | None
) -> Iterator[Any]:
    workers = min(len(items), os.cpu_count() or 1) or 1
    with ThreadPoolExecutor(max_workers=workers) as pool:
        # in the items' order, whichever ends first: a job welds its blocks in that order,
        # and the same volume makes the same model every time (in the order they ended, a
        # job decimated in blocks kept 139,124-139,164 triangles of CThead over five runs)
        futures = [pool.submit(task, shared, item) for item in items]
        if then is None:
            for future in futures:
                yield future.result()
            return
        results: list[Any] = []
        for future in futures:
            results.append(future.result())
            yield _FIRST_WAVE
        look, decide = then
        finish = decide([look(r) for r in results])
        seconds = [pool.submit(finish, r) for r in results]
        results.clear()
        for future in seconds:
            yield future.result()


def _on_dask(
    task: Callable[..., Any],
    shared: Any,
    items: Sequence[Any],
    scheduler: str | None,
    then: Then | None,
) -> Iterator[Any]:
    from distributed import as_completed as dask_completed

    with _client(scheduler) as client, _hand_over() as folder:
        ref = client.scatter(shared, broadcast=True) if _in_memory(shared) else shared
        workers = _workers(client)
        size = _group_size(len(items), workers)
        groups = [list(items[i : i + size]) for i in range(0, len(items), size)]
        futures: list[Any] = [None] * len(groups)
        if then is None:
            each = partial(_each, task, folder=folder)
            made = _in_runs(client, workers, each, ref, groups, futures)
            for group in _results(f for _, f in made):
                yield from group
            return
        look, decide = then
        looks: list[Any] = [None] * len(groups)

        def look_at(indices: list[int], batch: list[Any]) -> None:  # where the blocks are
            keys = [f"miss-look-{i}" for i in indices]
            found = client.map(partial(_each_result, look), batch, key=keys, pure=False)
            for i, f in zip(indices, found, strict=True):
                looks[i] = f

        made = _in_runs(client, workers, partial(_each, task), ref, groups, futures, look_at)
        for i, future in made:
            if future.status == "error":
                yield from _results([future])  # raises BlockTaskFailed
            yield from [_FIRST_WAVE] * len(groups[i])
        finish = decide([seen for group in client.gather(looks) for seen in group])
        keys = [f"miss-finish-{i}" for i in range(len(futures))]
        seconds = client.map(
            partial(_each_result, finish, folder=folder),
            futures,
            key=keys,
            pure=False,
            retries=2,
        )
        # the first wave's results go once the second has used them
        looks.clear()
        futures.clear()
        for group in _results(dask_completed(seconds)):
            yield from group


#: Blocks one Dask task makes, at most, one after the other (neighbours: they share
#: chunks). A task costs the scheduler, the client and the worker some milliseconds
#: whatever it does; 8 blocks a task were the fastest on 1 and 2 workers (16 leave too
#: few tasks to even out).
_GROUP = 8


def _group_size(blocks: int, workers: dict[str, dict[str, Any]]) -> int:
    """Blocks a task: :data:`_GROUP`, fewer where that would leave under 4 tasks a worker
    thread (the last ones even out the workers' shares)."""
    threads = sum(int(w.get("nthreads", 1)) for w in workers.values()) or 1
    return max(1, min(_GROUP, blocks // (4 * threads)))


def _workers(client: Any) -> dict[str, dict[str, Any]]:
    """Every worker of the cluster: address -> what the scheduler knows of it."""
    try:
        info = client.scheduler_info(n_workers=-1)  # all, whatever the release's default
    except TypeError:  # a release before the argument, which lists them all
        info = client.scheduler_info()
    return info.get("workers", {})


def _each(
    task: Callable[..., Any], shared: Any, items: Sequence[Any], folder: str | None = None
) -> Any:
    """``task(shared, item)`` for each of ``items``, in order (one Dask task's blocks);
    left in ``folder`` when this worker sees it (:func:`_left`)."""
    return _left([task(shared, item) for item in items], folder)


def _each_result(
    function: Callable[[Any], Any], results: Sequence[Any], folder: str | None = None
) -> Any:
    """``function(result)`` for each of one task's ``results``, in order (as :func:`_each`)."""
    return _left([function(result) for result in results], folder)


@contextmanager
def _hand_over() -> Iterator[str | None]:
    """A new folder in shared memory (``/dev/shm``) where the workers on this machine
    leave their results for the job's process (:func:`_left`), removed on leaving with
    whatever is still in it; None where there is no such memory (the results travel over
    the socket: a folder on disk would not be faster)."""
    import tempfile

    if not (os.path.isdir(_SHM) and os.access(_SHM, os.W_OK)):
        yield None
        return
    with tempfile.TemporaryDirectory(prefix="miss-blocks-", dir=_SHM) as folder:
        yield folder


#: Linux's shared memory, a folder of files held in memory.
_SHM = "/dev/shm"


@dataclass(frozen=True)
class _Left:
    """A task's results left in a file (:func:`_left`): the pickle without its arrays'
    memory, which lies in the file at ``offsets``."""

    path: str
    header: bytes
    offsets: tuple[tuple[int, int], ...]


#: Arrays start at multiples of this in a :class:`_Left` file.
_ALIGN = 64
#: Results whose arrays hold fewer bytes than this travel over the socket.
_SMALL = 1 << 16


def _left(results: Any, folder: str | None) -> Any:
    """``results`` written to a new file in ``folder`` (their arrays' memory as it is,
    after a pickle of the rest), a :class:`_Left` naming it returned instead; ``results``
    themselves where this worker does not see ``folder`` (another machine), where their
    arrays are small (:data:`_SMALL`), or would take more than a quarter of its free
    space, or it is full.

    A worker on the job's machine thus hands its meshes over through shared memory: the
    job's process maps the file (:func:`_taken`) instead of receiving them over a socket,
    which cost it a copy and fresh zeroed pages for every mesh.
    """
    if folder is None or not os.path.isdir(folder):
        return results
    import pickle
    import uuid

    buffers: list[pickle.PickleBuffer] = []
    header = pickle.dumps(results, protocol=5, buffer_callback=buffers.append)
    raws = [buffer.raw() for buffer in buffers]
    size = sum(raw.nbytes + _ALIGN for raw in raws)
    if size < _SMALL:
        return results  # a file would cost more than the bytes (a block's value range)
    space = os.statvfs(folder)
    if size > space.f_bavail * space.f_frsize // 4:
        return results  # shared memory is scarce (a container's 64 MB /dev/shm): leave it
    path = os.path.join(folder, uuid.uuid4().hex)
    try:
        offsets = _write_buffers(path, raws)
    except OSError:  # full: the results travel the usual way
        with suppress(OSError):
            os.unlink(path)
        return results
    return _Left(path, header, offsets)


def _write_buffers(path: str, raws: list[memoryview]) -> tuple[tuple[int, int], ...]:
    """``raws`` written to a new file one after the other, each at a multiple of
    :data:`_ALIGN`; their (offset, size)."""
    offsets, at = [], 0
    with open(path, "xb") as file:
        for raw in raws:
            start = -(-at // _ALIGN) * _ALIGN
            if start > at:
                file.write(bytes(start - at))
            file.write(raw)
            offsets.append((start, raw.nbytes))
            at = start + raw.nbytes
    return tuple(offsets)


def _taken(results: Any) -> Any:
    """The results a task left (:func:`_left`), their arrays read-only views of the file
    mapped here (the file is removed; the memory goes with the last view); any other
    result as it is."""
    if not isinstance(results, _Left):
        return results
    import mmap
    import pickle

    with open(results.path, "rb") as file:
        size = os.fstat(file.fileno()).st_size
        mapped = (
            mmap.mmap(
                file.fileno(), size, flags=mmap.MAP_SHARED | getattr(mmap, "MAP_POPULATE", 0),
                prot=mmap.PROT_READ,
            )
            if size
            else b""
        )  # fmt: skip
    os.unlink(results.path)
    view = memoryview(mapped)
    return pickle.loads(results.header, buffers=[view[a : a + n] for a, n in results.offsets])


#: Tasks handed to a worker at a time (:func:`_in_runs`), in one message to the scheduler
#: (which runs in the job's process for a local cluster): few, so that a worker done
#: with its own run finds some of the others' left to take.
_BATCH = 2


def _in_runs(
    client: Any,
    info: dict[str, dict[str, Any]],
    task: Callable[..., Any],
    ref: Any,
    items: Sequence[Any],
    futures: list[Any],
    submitted: Callable[[list[int], list[Any]], None] | None = None,
) -> Iterator[tuple[int, Any]]:
    """Run ``task(ref, item)`` for every item on the cluster, each worker (``info``:
    :func:`_workers`) along its own run of the items, and yield (index, future) as each
    ends (``futures[index]`` is set as it is submitted; ``submitted(indices, futures)``
    is called for each batch too).

    The items are blocks (or groups of them) in order, neighbours in space next to each
    other: neighbours read the chunks on their seam, which a worker decompresses once for
    both when it makes both (its chunk cache, :data:`miss.surface.blocks.CHUNKS`). So each worker
    gets an equal run of consecutive items, a few at a time (:data:`_BATCH` more once it
    has no more than one a thread left); one that has finished its run takes the far end
    of the longest run left. The work evens out without Dask's work stealing, which the
    blocks' uneven cost defeated: submitted all at once, a block's neighbour mostly went
    to the other worker, which decompressed the seam's chunks again; with one fixed run
    each, one worker finished long before the other.

    A worker is a preference, not a restriction: an item whose worker has gone runs on
    another (and so do the next ones of its run).
    """
    from collections import deque

    from distributed import as_completed as dask_completed

    workers: list[str | None] = [*sorted(info)] or [None]  # none yet: all at once, anywhere
    n, count = len(items), len(workers)
    threads = [int(info[w].get("nthreads", 1)) if w else n for w in workers]
    runs = [deque(range(n * k // count, n * (k + 1) // count)) for k in range(count)]
    owner: dict[str, int] = {}
    waiting = [0] * count  # submitted to each worker and not finished
    finished = dask_completed()

    def top_up(k: int) -> None:
        indices: list[int] = []
        while waiting[k] + len(indices) < threads[k] + _BATCH:
            if runs[k]:
                indices.append(runs[k].popleft())
                continue
            longest = max(runs, key=len)  # its own run is done: the far end of another
            if not longest:
                break
            indices.append(longest.pop())
        if not indices:
            return
        batch = client.map(
            task, [ref] * len(indices), [items[i] for i in indices], pure=False, retries=2,
            key=[f"miss-block-{i}" for i in indices],
            workers=None if workers[k] is None else [workers[k]], allow_other_workers=True,
        )  # fmt: skip
        for i, future in zip(indices, batch, strict=True):
            futures[i] = future
            owner[future.key] = k
        waiting[k] += len(batch)
        finished.update(batch)
        if submitted is not None:
            submitted(indices, batch)

    for k in range(count):
        top_up(k)
    for future in finished:
        k = owner.pop(future.key)
        waiting[k] -= 1
        if waiting[k] <= threads[k]:
            top_up(k)
        yield int(future.key.rsplit("-", 1)[1]), future


def _results(futures: Iterable[Any], release: bool = True) -> Iterator[Any]:
    """Each future's result as it finishes; a failure as :class:`BlockTaskFailed`."""
    for future in futures:
        try:
            result = future.result()
        except Exception as exc:  # KilledWorker, a task's own error
            raise BlockTaskFailed(
                f"a block task failed on the Dask cluster ({type(exc).__name__}: {exc}); "
                "check the workers' logs and that they can read the data folder."
            ) from exc
        finally:
            if release:
                future.release()
        yield _taken(result)


def _in_memory(shared: Any) -> bool:
    import numpy as np

    return isinstance(getattr(shared, "data", None), np.ndarray)


@contextmanager
def _client(scheduler: str | None) -> Iterator[Any]:
    """A Client to ``scheduler``, or to a LocalCluster started (and stopped) here."""
    from distributed import Client

    if scheduler is None:
        with local_cluster(os.cpu_count() or 1) as local, Client(local) as client:
            yield client
        return
    try:
        client = Client(scheduler, timeout="5s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise SchedulerUnreachable(
            f"cannot reach the Dask scheduler at {scheduler} ({exc}); start it there "
            f"(`dask scheduler`), fix the address, or unset {SCHEDULER_ENV} / drop --scheduler "
            "to run on this machine."
        ) from exc
    with client:
        yield client


@contextmanager
def local_cluster(workers: int) -> Iterator[Any]:
    """A LocalCluster of ``workers`` single-threaded worker processes, set up as MISS runs
    blocks (:data:`CLUSTER_CONFIG`, :data:`PRELOAD`); stopped on leaving."""
    import dask
    from distributed import LocalCluster

    with (
        dask.config.set(CLUSTER_CONFIG),
        LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            preload=PRELOAD,
        ) as local,
    ):
        yield local
