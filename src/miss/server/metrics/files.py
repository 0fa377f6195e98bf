"""Prometheus samples shared by the server processes of one host: each process writes its
own files in the data folder's ``run/metrics/<host>/`` and ``/metrics``, on any of them,
reads them all, summed.

This is prometheus_client's multiprocess mode (its file format, one file per kind and
process, read back by its :class:`MultiProcessCollector`) with the folder and the file
names chosen per app: the library's own mode is one folder per process, fixed by
``PROMETHEUS_MULTIPROC_DIR`` when it is imported, and the tests run many apps in one
process. A file is named after its process id and a tag of its app
(``counter_1234-9f3a0c1e.db``), so two apps of one test process never add to each
other's counts, and a sweep can tell which files belong to processes no longer running.

What the merge does with each kind is the library's: counters and histograms of every
file are summed, those of processes that have exited included (a total never goes back
while any server runs); ``livesum`` gauges are summed over the files of the running
processes only: a process that stops removes its own (:meth:`SampleFiles.close`), a
killed one's are left out of the sums (its process id no longer runs) and swept at the
next start.
"""

from __future__ import annotations

import os
import re
import secrets
import socket
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from prometheus_client.mmap_dict import MmapedDict, mmap_key
from prometheus_client.multiprocess import MultiProcessCollector
from prometheus_client.registry import Collector
from prometheus_client.utils import floatToGoString


def host_folder(data_dir: Path) -> Path:
    """``run/metrics/<host name>/`` in the data folder: process ids mean something on one
    host only, and several hosts may share a data folder (PostgreSQL)."""
    host = re.sub(r"[^A-Za-z0-9.-]", "-", socket.gethostname()) or "host"
    return data_dir / "run" / "metrics" / host


class SampleFiles:
    """One app's files in ``folder``: its values, kept in memory and written through on
    every change (an ``mmap`` write, no system call). Thread-safe."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.name = f"{os.getpid()}-{secrets.token_hex(4)}"
        self._files: dict[str, MmapedDict] = {}
        self._values: dict[tuple[str, str], float] = {}
        self._lock = threading.Lock()
        self._closed = False

    def add(self, kind: str, key: str, amount: float) -> None:
        """Add ``amount`` to the sample ``key`` of file ``kind`` (a counter, a histogram)."""
        with self._lock:
            value = self._values.get((kind, key), 0.0) + amount
            self._write(kind, key, value)

    def set(self, kind: str, key: str, value: float) -> None:
        """Set the sample ``key`` of file ``kind`` to ``value`` (a gauge)."""
        with self._lock:
            self._write(kind, key, value)

    def _write(self, kind: str, key: str, value: float) -> None:
        self._values[kind, key] = value
        if self._closed:
            return
        file = self._files.get(kind)
        if file is None:
            self.folder.mkdir(parents=True, exist_ok=True)
            file = self._files[kind] = MmapedDict(str(self.folder / f"{kind}_{self.name}.db"))
        file.write_value(key, value, 0.0)

    def sweep(self, alone: bool) -> None:
        """Drop the files of processes that are gone. ``alone`` (no other server runs on the
        data folder: the first to start): every file but this app's, so the counts start
        again from zero as after any restart; else only the live gauges of processes no
        longer running on this host (a killed one could not remove them)."""
        if not self.folder.is_dir():
            return
        for path in self.folder.glob("*.db"):
            owner = _owner(path)
            if owner == self.name:
                continue
            if alone or (path.name.startswith("gauge_live") and not _running(owner)):
                path.unlink(missing_ok=True)

    def close(self) -> None:
        """The app stops: its live gauges stop counting, its counters stay in the sums."""
        with self._lock:
            self._closed = True
            for kind, file in self._files.items():
                file.close()
                if kind.startswith("gauge_live"):
                    (self.folder / f"{kind}_{self.name}.db").unlink(missing_ok=True)
            self._files.clear()


def _running(owner: str) -> bool:
    """Whether the process of a file's owner (``<pid>-<tag>``) runs on this host."""
    try:
        os.kill(int(owner.split("-", 1)[0]), 0)
    except (ValueError, ProcessLookupError):
        return False
    except PermissionError:
        return True
    return True


class SharedCounter:
    """A counter with labels, e.g. ``inc("GET", "/api/models", "200")``."""

    def __init__(self, files: SampleFiles, name: str, doc: str, labels: Sequence[str]) -> None:
        self.files, self.name, self.doc, self.labels = files, name, doc, list(labels)

    def inc(self, *values: str, amount: float = 1.0) -> None:
        """Add ``amount`` to the counter for the label values ``values``."""
        key = mmap_key(self.name, self.name + "_total", self.labels, list(values), self.doc)
        self.files.add("counter", key, amount)


class SharedHistogram:
    """A histogram with labels. The files hold each bucket's own count (not cumulative,
    as the library's do): the merge sums the processes, then accumulates."""

    def __init__(
        self,
        files: SampleFiles,
        name: str,
        doc: str,
        labels: Sequence[str],
        buckets: Sequence[float],
    ) -> None:
        self.files, self.name, self.doc, self.labels = files, name, doc, list(labels)
        self.bounds = [*sorted(buckets), float("inf")]

    def observe(self, *values: str, value: float) -> None:
        """Count one observation of ``value`` (seconds, bytes: the histogram's unit) for the
        label values ``values``."""
        bound = next(b for b in self.bounds if value <= b)
        labels, label_values = [*self.labels, "le"], [*values, floatToGoString(bound)]
        bucket = mmap_key(self.name, self.name + "_bucket", labels, label_values, self.doc)
        self.files.add("histogram", bucket, 1.0)
        total = mmap_key(self.name, self.name + "_sum", self.labels, list(values), self.doc)
        self.files.add("histogram", total, value)


class SharedLiveSum:
    """A gauge without labels that ``/metrics`` sums over the running processes."""

    def __init__(self, files: SampleFiles, name: str, doc: str) -> None:
        self.files, self.key = files, mmap_key(name, name, [], [], doc)

    def set(self, value: float) -> None:
        """Set this process's share of the gauge."""
        self.files.set("gauge_livesum", self.key, value)


class FolderCollector(Collector):
    """Every process's samples in ``folder``, merged (``MultiProcessCollector.merge``)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder

    def collect(self) -> Iterator[Any]:
        """The samples of every process's files in the folder (those of live-sum gauges only
        for processes that still run), merged."""
        files = [
            str(path)
            for path in self.folder.glob("*.db")
            if _size(path) >= 8  # one a process is making may still be empty
            and not (path.name.startswith("gauge_live") and not _running(_owner(path)))
        ]
        yield from MultiProcessCollector.merge(files, accumulate=True)


def _owner(path: Path) -> str:
    """``<pid>-<tag>`` of ``<kind>_<pid>-<tag>.db``."""
    return path.name.rsplit("_", 1)[-1].removesuffix(".db")


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except FileNotFoundError:
        return 0
