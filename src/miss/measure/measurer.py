"""Measuring in a second process, for a fresh process that would otherwise wait for numba.

Only where the native kernels (:mod:`miss.measure._native`) were not built: with them a fresh
process measures on a thread of its own and starts no numba anywhere.

A job that decimates unmeasured and measures after (``miss convert --measure`` under the
paper's schedule) needs numba only for the measurement, and in a fresh process numba's
start (its import and its first kernel: about 0.8 s on the 2-core test machine) was most
of what measuring added to the job. A thread cannot start it meanwhile: the import holds
the GIL, and the decimation waited for it. A child process can, on the other core: it
imports numba and loads the measurement's kernels while this process reads the volume
and makes the surface; it gets each part's surface before decimation as soon as it
exists and makes its half of the measurement (:func:`miss.measure._jit.side_of`); it gets
the decimated part after and answers with the figures. The same code with the same
samples: the same figures to the bit.

A process that has numba loaded already (a server's warmed-up worker) measures on a
thread instead (:func:`miss.decimate.measuring_later`). Anything amiss with the child
(it cannot start, dies, answers nonsense) and the measurement is made here.

The child is this package's own code run by the same interpreter; the pipe carries only
what this process sends it (pickled arrays) and its answers.
"""

from __future__ import annotations

import atexit
import contextlib
import itertools
import os
import pickle
import subprocess
import sys
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, BinaryIO

from miss._process import LEAN_ENV
from miss.measure import native

if TYPE_CHECKING:
    from miss.spec import JobSpec
    from miss.types import Mesh


class MeasurerGone(RuntimeError):
    """The child cannot answer (not started, exited, or sent something unexpected)."""


class Measurer:
    """One child process that measures deviations; parts go to it one after another."""

    def __init__(self) -> None:
        # the child imports this same tree of miss, wherever it was found
        here = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        path = os.pathsep.join(p for p in (here, os.environ.get("PYTHONPATH", "")) if p)
        env = {**os.environ, "PYTHONPATH": path, LEAN_ENV: "1"}  # it loads what it needs
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "miss.measure.measurer"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env,
        )  # fmt: skip
        # Writes go through one thread: a pipe takes 64 KB before the child reads, and the
        # child reads nothing until numba has started.
        self._writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="miss-measurer")
        self._read = threading.Lock()
        self._keys = itertools.count()
        self._failed = False

    def _send(self, message: tuple[Any, ...]) -> Future[None]:
        stdin = self.proc.stdin
        assert stdin is not None

        def write() -> None:
            pickle.dump(message, stdin, protocol=pickle.HIGHEST_PROTOCOL)
            stdin.flush()

        return self._writer.submit(write)

    def side(self, before: Mesh, samples: int) -> RemoteSide:
        """Send ``before`` (a part's surface before decimation): the child makes its half
        of the measurement while this process decimates."""
        key = next(self._keys)
        sent = self._send(("side", key, before.vertices, before.faces, samples))
        return RemoteSide(self, key, sent)

    def _deviation(self, key: int, after: Mesh) -> tuple[float, float]:
        if self._failed:
            raise MeasurerGone("the measuring process failed before")
        try:
            self._send(("deviation", key, after.vertices, after.faces)).result()
            with self._read:
                assert self.proc.stdout is not None
                answer = pickle.load(self.proc.stdout)
        except Exception as exc:  # a broken pipe, EOF, a truncated answer
            self._failed = True
            raise MeasurerGone(f"the measuring process did not answer ({exc!r})") from exc
        if (
            not isinstance(answer, tuple)
            or len(answer) != 4
            or answer[0] != key
            or not all(isinstance(x, (int, float)) for x in answer[1:])
        ):
            self._failed = True
            raise MeasurerGone(f"the measuring process answered {answer!r:.200}")
        return float(answer[1]), float(answer[2])

    def close(self) -> None:
        """End the child: its stdin closed, it exits by itself. Not waited for: a process
        with numba takes a while to exit, and the command would wait that long."""
        self._writer.shutdown(wait=False, cancel_futures=True)
        with contextlib.suppress(OSError):
            if self.proc.stdin is not None:
                self.proc.stdin.close()


class RemoteSide:
    """A part's half of a measurement, made in the :class:`Measurer`'s child."""

    def __init__(self, measurer: Measurer, key: int, sent: Future[None]) -> None:
        self.measurer, self.key, self.sent = measurer, key, sent

    def deviation(self, after: Mesh) -> tuple[float, float]:
        """The deviation of ``after`` (this part decimated) from the surface sent before,
        max and mean, mm (:func:`miss.measure._jit.deviation`'s); :class:`MeasurerGone` if the
        child cannot say. Not a ``Deviation``: its module would load numba here."""
        try:
            self.sent.result()
        except Exception as exc:
            raise MeasurerGone(
                f"the surface did not reach the measuring process ({exc!r})"
            ) from exc
        return self.measurer._deviation(self.key, after)


_SHARED: list[Measurer] = []
_LOCK = threading.Lock()


def shared() -> Measurer | None:
    """This process's measurer: started on the first call; one per process, ended at
    exit. None where it cannot start, or once it has failed (its parts are measured here
    then)."""
    with _LOCK:
        if not _SHARED:
            try:
                _SHARED.append(Measurer())
            except OSError:
                return None
            atexit.register(_SHARED[0].close)
        return None if _SHARED[0]._failed else _SHARED[0]


def wanted(spec: JobSpec, measure: bool) -> bool:
    """Whether a job of ``spec``, measured after its files when ``measure``, in this
    process, would send its parts here: a paper-schedule decimation of threshold surfaces
    (a guaranteed one is checked as it runs, with numba here; label parts are measured
    after), in a process without numba, where the native kernels were not built (with
    them the process measures on a thread of its own, no numba started anywhere)."""
    decimation = spec.decimation
    return (
        measure
        and decimation.schedule == "paper"
        and decimation.method != "none"
        and any(item.level is not None for item in spec.structures.items)
        and "numba" not in sys.modules
        and not native()
    )


def prestart(spec: JobSpec, measure: bool) -> None:
    """Start the measurer now when a job of ``spec`` about to start will use it (see
    :func:`wanted`): its numba starts while this process loads the volume and its own
    libraries."""
    if wanted(spec, measure):
        shared()


# ------------------------------------------------------------------------------ the child

#: Surfaces the child keeps waiting for their decimated parts, the newest: a job sends at
#: most :data:`miss.structures.build.SIDES_AHEAD` (8) before it asks for their figures;
#: older ones belong to jobs that failed.
KEPT = 16


def serve(stdin: BinaryIO, stdout: BinaryIO) -> None:
    """The child's loop: ``("side", key, vertices, faces, samples)`` makes that surface's
    half; ``("deviation", key, vertices, faces)`` answers ``(key, max_mm, mean_mm,
    samples)``; end of input ends it."""
    import numpy as np

    from miss.measure import deviation, side_of
    from miss.types import Mesh

    # numba's start and the kernels' load, before the first surface comes
    ball = Mesh(
        vertices=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float32),
        faces=np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int32),
    )
    deviation(ball, ball, samples=8)
    deviation(ball, ball, samples=8, side=side_of(ball, 8))
    befores: dict[int, tuple[Mesh, Any, int]] = {}
    while True:
        try:
            message = pickle.load(stdin)
        except EOFError:
            return
        if message[0] == "side":
            _, key, vertices, faces, samples = message
            for old in [k for k in befores if k < key - KEPT]:  # parts of jobs that failed
                del befores[old]
            before = Mesh(vertices=vertices, faces=faces)
            try:
                side = side_of(before, samples)
            except MemoryError:
                side = None  # made with the rest, when the decimated part comes
            befores[key] = (before, side, samples)
        else:
            _, key, vertices, faces = message
            before, side, samples = befores.pop(key)
            dev = deviation(before, Mesh(vertices=vertices, faces=faces), samples, side=side)
            pickle.dump((key, dev.max_mm, dev.mean_mm, dev.samples), stdout)
            stdout.flush()


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt, BrokenPipeError):
        serve(sys.stdin.buffer, sys.stdout.buffer)
