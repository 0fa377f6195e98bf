"""Receiving an upload: the multipart body streamed to disk, a few at a time.

The body is parsed as it arrives and the file part written straight into the data
folder's ``tmp/``, counting bytes, so an upload over the limit stops at the limit and
a 2 GB DICOM series never sits in memory. It must keep arriving (:class:`Pace`): a body
that trickles or stalls is answered 408 and gives its slot back, so a few slow clients
cannot hold the server's upload slots (:class:`UploadSlots`) for everyone. What it holds is read afterwards by a
confined child process (:mod:`miss.io.confined`; zips by :mod:`miss.io.archive`).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import os
import re
import shutil
import time
from collections import deque
from collections.abc import AsyncGenerator
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import IO, Any

from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect, Request
from starlette.types import Message, Receive

from miss.errors import BadParameter, UnsupportedFormat
from miss.io.archive import too_large
from miss.server.core.errors import UploadTooLarge, UploadTooSlow
from miss.server.core.ratelimit import HeldCounts, OverLimit
from miss.server.storage.store import is_disk_full

CHUNK = 1 << 20
#: Seconds within which arrivals share one mark of an upload's pace.
MARK_EVERY = 0.25
FIELD_LIMIT = 64 * 1024
MAX_FIELDS = 16
#: Files one upload may hold (a folder of slices sent as several ``file`` parts).
MAX_FILES = 100_000
#: The folder several files of one upload are gathered in: where a zip is unpacked, so
#: the confined reader takes them as it takes an unpacked zip.
GATHERED = "unzipped"
_UNSAFE_CHARS = re.compile(r"[^A-Za-z0-9._-]+")


@dataclass
class Upload:
    """The file part saved to ``path`` and the small text fields sent beside it."""

    path: Path | None = None
    filename: str = ""
    size: int = 0
    fields: dict[str, str] = field(default_factory=dict)


def safe_filename(name: str) -> str:
    """The base name with only harmless characters; keeps the suffixes readers sniff."""
    base = PurePosixPath(name.replace("\\", "/")).name
    clean = _UNSAFE_CHARS.sub("_", base)[-120:].rstrip("._")
    if not clean.strip("._"):
        return "upload.bin"
    # A name of foreign letters only ("снимок.nii.gz" -> "_.nii.gz") must keep its suffix.
    return "upload" + clean if clean[0] in "._" else clean


class _MultipartSink:
    """Callbacks for python-multipart: the ``file`` part to disk, other fields to memory.
    With ``many``, several ``file`` parts (the slices of a series, a header and its data
    file) are gathered into one folder, :data:`GATHERED`, counted against one ``limit``."""

    def __init__(self, boundary: bytes, folder: Path, limit: int, many: bool = False) -> None:
        self.upload = Upload()
        self.folder, self.limit, self.many = folder, limit, many
        self.files = 0
        self._headers: dict[bytes, bytes] = {}
        self._header = [b"", b""]
        self._out: IO[bytes] | None = None
        self._field: tuple[str, bytearray] | None = None
        callbacks: Any = {
            "on_part_begin": self._part_begin,
            "on_header_field": self._header_field,
            "on_header_value": self._header_value,
            "on_header_end": self._header_end,
            "on_headers_finished": self._headers_finished,
            "on_part_data": self._part_data,
            "on_part_end": self._part_end,
        }
        self.parser = MultipartParser(boundary, callbacks)

    def _part_begin(self) -> None:
        self._headers, self._header = {}, [b"", b""]

    def _header_field(self, data: bytes, start: int, end: int) -> None:
        self._header[0] += data[start:end]

    def _header_value(self, data: bytes, start: int, end: int) -> None:
        self._header[1] += data[start:end]

    def _header_end(self) -> None:
        self._headers[self._header[0].strip().lower()] = self._header[1].strip()
        self._header = [b"", b""]

    def _headers_finished(self) -> None:
        _, params = parse_options_header(self._headers.get(b"content-disposition", b""))
        name = params.get(b"name", b"").decode("utf-8", "replace")
        filename = params.get(b"filename")
        if name != "file":
            if len(self.upload.fields) >= MAX_FIELDS:
                raise BadParameter(
                    f"too many form fields; send 'file' and at most {MAX_FIELDS} others."
                )
            self._field = (name, bytearray())
            return
        if filename is None or (self.upload.path is not None and not self.many):
            raise BadParameter("send exactly one file, in the multipart field 'file'.")
        name = filename.decode("utf-8", "replace")
        self.files += 1
        if self.files == 1:
            self.upload.filename = name
            self.upload.path = target = self.folder / safe_filename(name)
        else:
            target = self._gathered(name)
        self._out = open(target, "wb")  # noqa: SIM115 - closed in _part_end/close

    def _gathered(self, name: str) -> Path:
        """Where the next file of several goes: the folder :data:`GATHERED` (the first
        file moved into it at the second), under a name no earlier file took."""
        if self.files > MAX_FILES:
            raise BadParameter(
                f"the upload holds more than {MAX_FILES} files; send one series at a time."
            )
        gathered = self.folder / GATHERED
        assert self.upload.path is not None
        if self.upload.path != gathered:
            gathered.mkdir()
            self.upload.path.rename(gathered / self.upload.path.name)
            self.upload.path = gathered
        self.upload.filename = f"{self.files} files"
        target = gathered / safe_filename(name)
        if target.exists():  # the same name from two folders of a drop
            target = gathered / f"{self.files}-{target.name}"
        return target

    def _part_data(self, data: bytes, start: int, end: int) -> None:
        if self._out is not None:
            self.upload.size += end - start
            if self.upload.size > self.limit:
                raise UploadTooLarge(too_large("upload", self.limit))
            self._out.write(data[start:end])
        elif self._field is not None:
            self._field[1].extend(data[start:end])
            if len(self._field[1]) > FIELD_LIMIT:
                raise BadParameter(
                    f"form field {self._field[0]!r} is longer than {FIELD_LIMIT} bytes."
                )

    def _part_end(self) -> None:
        if self._field is not None:
            self.upload.fields[self._field[0]] = self._field[1].decode("utf-8", "replace")
            self._field = None
        self.close()

    def write(self, chunk: bytes) -> None:
        self.parser.write(chunk)

    def finish(self, chunk: bytes) -> Upload:
        if chunk:
            self.parser.write(chunk)
        self.parser.finalize()
        self.close()
        if self.upload.path is None:
            raise BadParameter("no file in the upload; send it in the multipart field 'file'.")
        return self.upload

    def close(self) -> None:
        if self._out is not None:
            out, self._out = self._out, None
            out.close()

    def discard(self) -> None:
        """Close and delete the file part (a full disk: give the space back now)."""
        with contextlib.suppress(OSError):  # closing flushes, which fails on a full disk
            self.close()
        if self.upload.path is not None and self.upload.path.is_dir():
            shutil.rmtree(self.upload.path, ignore_errors=True)
        elif self.upload.path is not None:
            self.upload.path.unlink(missing_ok=True)


class UploadSlots:
    """Uploads being received or read at once: at most ``per_user`` for one account and
    ``in_all`` for everyone. Each takes disk, a reader process and memory until it is
    stored, so a client over the limit hears 429 with a Retry-After at once, before it
    sends a byte more.

    An account's uploads beyond its first never take the last free slot: that one is
    kept for an account sending nothing yet, so two accounts (of slow links, or
    trickling on purpose) cannot fill the server for a third; holding ``in_all``
    slots takes ``in_all`` accounts, each pushing at least the minimum rate (:class:`Pace`)."""

    #: Seconds a refused client is told to wait (a typical upload's reading time).
    RETRY_SECONDS = 10.0

    def __init__(self, per_user: int, in_all: int) -> None:
        self.per_user, self.in_all = per_user, in_all
        self._users = HeldCounts()

    def slot(self, user_id: str) -> contextlib.AbstractContextManager[None]:
        """Hold one of ``user_id``'s uploads while the body runs; :class:`OverLimit`
        beyond the limits above."""
        return self._users.hold(user_id, self._check)

    def _check(self, mine: int, total: int) -> None:
        if mine >= self.per_user:
            raise OverLimit(
                f"too many uploads at once: this account is already sending {mine} "
                f"(at most {self.per_user}); wait for one to finish, then send this again.",
                self.RETRY_SECONDS,
            )
        if mine and total + 1 >= self.in_all:
            raise OverLimit(
                f"too many uploads at once: this account is already sending {mine} and "
                f"the server's last free upload slot (of {self.in_all}) is kept for "
                "accounts sending nothing; wait for yours to finish, then send this again.",
                self.RETRY_SECONDS,
            )
        if total >= self.in_all:
            raise OverLimit(
                f"the server is already receiving {total} uploads (at most "
                f"{self.in_all} at once); send this again in a few seconds.",
                self.RETRY_SECONDS,
            )


@dataclass(frozen=True)
class Pace:
    """The least an upload's body must keep up: ``min_rate`` bytes per second on average
    over every ``window`` seconds once the first have passed (0: no minimum), and never
    ``idle`` seconds without a byte. Both are far below any real link: they only end
    bodies that trickle or stall (408)."""

    min_rate: float = 0.0
    window: float = 30.0
    idle: float = 60.0

    #: Longest wait between two checks of the rate, s.
    CHECK_EVERY = 1.0

    def check(self, start: float, now: float, marks: deque[tuple[float, int]]) -> None:
        """Raise :class:`UploadTooSlow` when the body is behind; ``marks`` holds (time,
        bytes so far) at each arrival, oldest first; those the window has left behind
        are dropped (one before it is kept, the start of the span measured)."""
        if now - marks[-1][0] >= self.idle:
            raise UploadTooSlow(
                f"the upload stalled: no data for {self.idle:g} s, so it was stopped and "
                "nothing was kept; check the connection and send it again."
            )
        while len(marks) > 1 and marks[1][0] <= now - self.window:
            marks.popleft()
        if not self.min_rate or now - start < self.window:
            return
        since, got = marks[0][0], marks[-1][1] - marks[0][1]
        if got < self.min_rate * (now - since):
            raise UploadTooSlow(
                f"the upload arrived at {got / max(now - since, 1e-9) / 1000:.2f} kB/s over the "
                f"last {now - since:.0f} s, below the minimum of {self.min_rate / 1000:g} "
                "kB/s, so it was stopped and nothing was kept; send it again over a "
                "faster connection."
            )


async def paced(receive: Receive, pace: Pace) -> AsyncGenerator[bytes, None]:
    """The request body's chunks as they arrive, raising :class:`UploadTooSlow` as soon as
    it falls behind ``pace``; checked while waiting for the next chunk too, since a client
    that sends nothing never wakes a plain ``async for``. Read from the ASGI ``receive``
    itself, as ``Request.stream`` does: a wait cut short to check the pace loses nothing
    there (the server keeps what comes for the next call)."""
    start = time.monotonic()
    marks: deque[tuple[float, int]] = deque([(start, 0)])
    wait = min(pace.idle, pace.window, pace.CHECK_EVERY)
    while True:
        message: Message | None = None
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(wait):
                message = await receive()
        now = time.monotonic()
        if message is None:
            pace.check(start, now, marks)
            continue
        if message["type"] == "http.disconnect":
            raise ClientDisconnect()
        if chunk := message.get("body", b""):
            _mark(marks, now, len(chunk))
            pace.check(start, now, marks)
            yield chunk
        if not message.get("more_body", False):
            return


def _mark(marks: deque[tuple[float, int]], now: float, size: int) -> None:
    """Note ``size`` bytes come at ``now``; arrivals close together share one mark, so a
    fast upload keeps a few marks a second, not one a chunk."""
    if len(marks) > 1 and now - marks[-1][0] < MARK_EVERY:
        marks[-1] = (now, marks[-1][1] + size)
    else:
        marks.append((now, marks[-1][1] + size))


async def receive(
    request: Request,
    folder: Path,
    limit: int,
    min_free: int = 0,
    pace: Pace | None = None,
    many: bool = False,
) -> Upload:
    """Stream a multipart/form-data body into ``folder``; the file part in field ``file``
    (with ``many``, several parts of that name gathered in one folder: ``Upload.path``).

    The disk's free space is checked as the body arrives, not only before: a client that
    fills the disk mid-upload gets 507 and its partial file is removed at once. A body
    that falls behind ``pace`` gets 408 (the caller removes what came of it)."""
    kind, params = parse_options_header(request.headers.get("content-type", ""))
    if kind != b"multipart/form-data" or not params.get(b"boundary"):
        raise UnsupportedFormat(
            "send the scan as multipart/form-data with the file in the field 'file' "
            "(e.g. curl -F file=@series.zip)."
        )
    length = request.headers.get("content-length", "")
    if length.isdigit() and int(length) > limit + FIELD_LIMIT:
        raise UploadTooLarge(too_large("upload", limit))
    sink = _MultipartSink(params[b"boundary"], folder, limit, many)
    pending = bytearray()
    full: OSError | None = None
    try:
        # Parsing and disk writes run in the threadpool, a megabyte at a time, so the event
        # loop keeps serving other requests during a long upload.
        async with contextlib.aclosing(paced(request.receive, pace or Pace())) as chunks:
            async for chunk in chunks:
                if full is not None:
                    continue  # read to the end, so the client hears "disk full", not a reset
                pending += chunk
                if len(pending) >= CHUNK:
                    data = bytes(pending)
                    full = await run_in_threadpool(_write_unless_full, sink, data, min_free)
                    pending.clear()
        if full is None:
            return await run_in_threadpool(sink.finish, bytes(pending))
        raise full
    except ClientDisconnect:
        raise BadParameter("the upload was interrupted before the end; send it again.") from None
    finally:
        sink.close()


def _free_bytes(folder: Path) -> int:
    stat = os.statvfs(folder)
    return stat.f_bavail * stat.f_frsize


def _write_unless_full(sink: _MultipartSink, data: bytes, min_free: int) -> OSError | None:
    """Write; on a full disk (or one below ``min_free`` bytes free) drop the partial file
    at once and return the error."""
    try:
        sink.write(data)
        if min_free and _free_bytes(sink.folder) < min_free:
            raise OSError(errno.ENOSPC, f"less than {min_free} bytes free")
    except OSError as exc:
        if not is_disk_full(exc):
            raise
        sink.discard()
        return exc
    return None
