"""Blockwise surfaces on a real Dask cluster: a ``dask scheduler`` and two ``dask worker``
processes on loopback, the tasks seen on both workers, a worker killed mid-job, an
address nobody answers."""

from __future__ import annotations

import errno
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from test_blocks import assert_same_surface, zarr_copy

from miss import Volume
from miss.surface.blockwise import blockwise_surface
from miss.surface.runner import SchedulerUnreachable

DASK = Path(sys.executable).with_name("dask")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Cluster:
    """A scheduler and two workers (no nanny: a killed worker stays dead)."""

    def __init__(self, folder: Path) -> None:
        self.address = f"tcp://127.0.0.1:{_free_port()}"
        port = self.address.rsplit(":", 1)[1]
        self.procs: list[subprocess.Popen[bytes]] = []
        self.logs = folder
        self._start("scheduler", ["scheduler", "--host", "127.0.0.1", "--port", port,
                                  "--no-dashboard"])  # fmt: skip
        self.workers = [
            self._start(
                f"worker{i}",
                [
                    "worker",
                    self.address,
                    "--nthreads",
                    "1",
                    "--no-nanny",
                    "--no-dashboard",
                    "--name",
                    f"w{i}",
                    "--local-directory",
                    str(folder / f"w{i}"),
                ],
            )  # fmt: skip
            for i in range(2)
        ]

    def _start(self, name: str, args: list[str]) -> subprocess.Popen[bytes]:
        log = (self.logs / f"{name}.log").open("wb")
        proc = subprocess.Popen([str(DASK), *args], stdout=log, stderr=log, cwd=self.logs)
        self.procs.append(proc)
        return proc

    def wait(self) -> dict[str, int]:
        """Worker address -> pid, once both workers have joined."""
        from distributed import Client

        with Client(self.address, timeout="30s") as client:
            client.wait_for_workers(2, timeout=60)
            return client.run(os.getpid)

    def stop(self) -> None:
        for proc in reversed(self.procs):
            if proc.poll() is None:
                proc.terminate()
        for proc in self.procs:
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[tuple[Cluster, dict[str, int]]]:
    if not DASK.exists():
        pytest.skip(f"no dask command beside {sys.executable} (install distributed)")
    folder = tmp_path / "cluster"
    folder.mkdir()
    running = Cluster(folder)
    try:
        yield running, running.wait()
    finally:
        running.stop()


@pytest.fixture(scope="module")
def cthead(datasets: Path) -> Volume:
    from miss.io import load_volume

    return load_volume(datasets / "ct_head_stanford_cthead" / "CThead.nhdr")


def test_tasks_run_on_both_workers_and_equal_the_local_run(cluster, cthead, tmp_path) -> None:
    from distributed import Client, get_task_stream

    running, workers = cluster
    lazy = zarr_copy(cthead, tmp_path, (64, 64, 32))
    local = blockwise_surface(lazy, 1500.0, normals=False, block=48, cluster=False)
    with Client(running.address) as client, get_task_stream(client) as stream:
        remote = blockwise_surface(lazy, 1500.0, normals=False, block=48, scheduler=running.address)
    ran = {t["worker"] for t in stream.data if str(t["key"]).startswith("miss-block")}
    assert ran == set(workers)
    assert_same_surface(remote, local, 0.0)


def _triangles_by_position(mesh) -> set[tuple[float, ...]]:
    return {tuple(sorted(map(tuple, t))) for t in mesh.vertices[mesh.faces].tolist()}


def test_blocks_decimated_on_the_workers_equal_the_local_run(cluster, cthead, tmp_path) -> None:
    """Both waves (each block's surface, then its decimation once the bound is known) run
    on the workers, and the welded result is the run on threads', vertex for vertex and
    triangle for triangle, though the blocks come back in another order: the decimation
    across the blocks starts from the same mesh, so the model is the same every run."""
    from distributed import Client, get_task_stream

    from miss.surface.blockwise import BlockDecimation, blockwise_decimated

    running, workers = cluster
    lazy = zarr_copy(cthead, tmp_path, (64, 64, 32))
    wanted = BlockDecimation("quadric", 0.9, 0.002)
    local, local_stage = blockwise_decimated(lazy, 1500.0, wanted, block=48, cluster=False)
    with Client(running.address) as client, get_task_stream(client) as stream:
        remote, stage = blockwise_decimated(
            lazy, 1500.0, wanted, block=48, scheduler=running.address
        )
    for wave in ("miss-block", "miss-finish"):
        assert {t["worker"] for t in stream.data if str(t["key"]).startswith(wave)} == set(workers)
    assert (stage.triangles_in, stage.triangles_out) == (
        local_stage.triangles_in,
        local_stage.triangles_out,
    )
    assert stage.max_mm == local_stage.max_mm
    assert _triangles_by_position(remote) == _triangles_by_position(local)
    np.testing.assert_array_equal(remote.vertices, local.vertices)
    np.testing.assert_array_equal(remote.faces, local.faces)


def test_each_worker_runs_its_own_run_of_neighbouring_blocks(cluster) -> None:
    """Neighbouring blocks share the chunks on their seam, which a worker decompresses once
    for both when it makes both: each worker gets a run of consecutive blocks (the far
    end of the other's run once its own is done), not every other one."""
    from miss.surface.runner import run_blocks

    running, workers = cluster

    def where(_: object, item: int) -> tuple[int, str]:
        import time

        from distributed import get_worker

        time.sleep(0.005 * (1 + item % 3))  # uneven, as blocks are
        return item, get_worker().address

    ran = dict(run_blocks(where, None, list(range(60)), scheduler=running.address))
    assert sorted(ran) == list(range(60))
    assert set(ran.values()) == set(workers)
    switches = sum(ran[i] != ran[i + 1] for i in range(59))
    assert switches <= 8, [ran[i][-5:] for i in range(60)]


def test_workers_on_this_machine_hand_meshes_over_through_shared_memory(cluster) -> None:
    """The workers (here on loopback, as a local cluster's are) leave each task's results
    in a file that the job's process maps: no copy over the socket. The arrays arrive
    whole and read-only, and no file is left behind."""
    import mmap

    import numpy as np

    from miss.surface.runner import run_blocks

    running, _ = cluster
    folders_before = set(Path("/dev/shm").glob("miss-blocks-*"))

    def block(_: object, item: int) -> tuple[int, np.ndarray, np.ndarray]:
        rng = np.random.default_rng(item)
        return (
            item,
            rng.random((5000 + item, 3)).astype(np.float32),
            np.asfortranarray(rng.integers(0, 5000, (6000, 3), dtype=np.int32)),
        )

    got = {
        i: (v, f) for i, v, f in run_blocks(block, None, list(range(24)), scheduler=running.address)
    }
    assert sorted(got) == list(range(24))
    for i, (verts, faces) in got.items():
        _, want_v, want_f = block(None, i)
        assert np.array_equal(verts, want_v) and np.array_equal(faces, want_f)
        assert faces.flags.f_contiguous
        base: object = verts
        while isinstance(base, np.ndarray | memoryview):
            base = base.obj if isinstance(base, memoryview) else base.base
        assert isinstance(base, mmap.mmap), f"the mesh came over the socket ({base!r})"
        assert not verts.flags.writeable
    assert set(Path("/dev/shm").glob("miss-blocks-*")) == folders_before


def test_results_travel_as_they_are_where_the_hand_over_folder_is_not_seen(
    tmp_path, monkeypatch
) -> None:
    """A worker on another machine (the folder does not exist there) or a full folder:
    the results go back over the socket, as before."""
    import numpy as np

    from miss.surface import runner

    results = [np.arange(10_000.0)]
    assert runner._left(results, str(tmp_path / "elsewhere")) is results
    small = [(0.0, 1.0), np.arange(10.0)]  # a block's range: not worth a file
    assert runner._left(small, str(tmp_path)) is small

    def full(path: str, raws: list[memoryview]) -> None:
        Path(path).write_bytes(bytes(raws[0])[:4])  # part of it, then the disk is full
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(runner, "_write_buffers", full)
    assert runner._left(results, str(tmp_path)) is results
    assert not any(tmp_path.iterdir())  # nothing half-written left
    monkeypatch.undo()
    scarce = os.statvfs_result((4096, 4096, 1000, 0, 0, 100, 10, 10, 0, 255))
    monkeypatch.setattr(os, "statvfs", lambda _: scarce)  # none free
    assert runner._left(results, str(tmp_path)) is results
    monkeypatch.undo()
    left = runner._left(results, str(tmp_path))
    assert isinstance(left, runner._Left)
    back = runner._taken(left)
    assert np.array_equal(back[0], results[0]) and not any(tmp_path.glob("[0-9a-f]*"))


def test_a_worker_killed_mid_job_leaves_the_job_to_the_other(cluster, cthead, tmp_path) -> None:
    running, workers = cluster
    lazy = zarr_copy(cthead, tmp_path, (32, 32, 16))
    local = blockwise_surface(lazy, 1500.0, normals=False, block=24, cluster=False)
    victim = next(iter(workers.values()))
    killed = threading.Event()

    def progress(stage: str, fraction: float) -> None:
        if fraction > 0.3 and not killed.is_set():
            os.kill(victim, signal.SIGKILL)
            killed.set()

    remote = blockwise_surface(
        lazy, 1500.0, normals=False, block=24, scheduler=running.address, progress=progress
    )
    assert killed.is_set()
    assert_same_surface(remote, local, 0.0)


def test_local_cluster_equals_threads(cthead) -> None:
    threads = blockwise_surface(cthead, 1500.0, normals=False, block=64, cluster=False)
    cluster = blockwise_surface(cthead, 1500.0, normals=False, block=64, cluster=True)
    assert_same_surface(cluster, threads, 0.0)


def test_unreachable_scheduler_names_the_address(cthead) -> None:
    address = f"tcp://127.0.0.1:{_free_port()}"
    start = time.perf_counter()
    with pytest.raises(SchedulerUnreachable, match=f"at {address}.*MISS_DASK_SCHEDULER"):
        blockwise_surface(cthead, 1500.0, block=64, scheduler=address)
    assert time.perf_counter() - start < 30


def test_cli_unreachable_scheduler_one_line_exit_2(datasets, tmp_path) -> None:
    address = f"tcp://127.0.0.1:{_free_port()}"
    head = datasets / "ct_head_stanford_cthead" / "CThead.nhdr"
    proc = subprocess.run(
        [sys.executable, "-m", "miss.cli", "convert", str(head), "--level", "1500",
         "-o", str(tmp_path / "bone.stl"), "--scheduler", address],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and address in lines[0] and "dask scheduler" in lines[0]
