"""Receiving an upload: the multipart body streamed to disk, zips unpacked safely.

The body is parsed as it arrives and the file part written straight into the data
folder's ``tmp/``, counting bytes, so an upload over the limit stops at the limit and
a 2 GB DICOM series never sits in memory. Zips are unpacked member by member with the
decompressed bytes counted too (a zip bomb stops at the limit), after checking that no
member would land outside the folder (``../``, absolute paths, symbolic links).
"""

from __future__ import annotations

import contextlib
import re
import stat
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import IO, Any

from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect, Request

from miss.errors import BadParameter, UnreadableVolume, UnsupportedFormat
from miss.io.dicom_files import MAX_ZIP_RATIO, RATIO_FLOOR
from miss.server.errors import UnsafeArchive, UploadTooLarge
from miss.server.store import is_disk_full

CHUNK = 1 << 20
FIELD_LIMIT = 64 * 1024
MAX_FIELDS = 16
MAX_MEMBERS = 100_000
#: Extensions of single-file volumes, longest first so ".nii.gz" wins over ".gz".
VOLUME_SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".nhdr", ".mha", ".mhd")
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
    """Callbacks for python-multipart: the ``file`` part to disk, other fields to memory."""

    def __init__(self, boundary: bytes, folder: Path, limit: int) -> None:
        self.upload = Upload()
        self.folder, self.limit = folder, limit
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
        if filename is None or self.upload.path is not None:
            raise BadParameter("send exactly one file, in the multipart field 'file'.")
        self.upload.filename = filename.decode("utf-8", "replace")
        self.upload.path = self.folder / safe_filename(self.upload.filename)
        self._out = open(self.upload.path, "wb")  # noqa: SIM115 - closed in _part_end/close

    def _part_data(self, data: bytes, start: int, end: int) -> None:
        if self._out is not None:
            self.upload.size += end - start
            if self.upload.size > self.limit:
                raise UploadTooLarge(_too_large("upload", self.limit))
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
        if self.upload.path is not None:
            self.upload.path.unlink(missing_ok=True)


def _too_large(what: str, limit: int) -> str:
    return (
        f"the {what} is larger than the limit of {limit / 2**20:g} MB; send a smaller "
        "series or raise MISS_MAX_UPLOAD_MB / MISS_MAX_UNZIPPED_MB on the server."
    )


async def receive(request: Request, folder: Path, limit: int) -> Upload:
    """Stream a multipart/form-data body into ``folder``; the file part in field ``file``."""
    kind, params = parse_options_header(request.headers.get("content-type", ""))
    if kind != b"multipart/form-data" or not params.get(b"boundary"):
        raise UnsupportedFormat(
            "send the scan as multipart/form-data with the file in the field 'file' "
            "(e.g. curl -F file=@series.zip)."
        )
    length = request.headers.get("content-length", "")
    if length.isdigit() and int(length) > limit + FIELD_LIMIT:
        raise UploadTooLarge(_too_large("upload", limit))
    sink = _MultipartSink(params[b"boundary"], folder, limit)
    pending = bytearray()
    full: OSError | None = None
    try:
        # Parsing and disk writes run in the threadpool, a megabyte at a time, so the event
        # loop keeps serving other requests during a long upload.
        async for chunk in request.stream():
            if full is not None:
                continue  # read to the end, so the client hears "disk full", not a reset
            pending += chunk
            if len(pending) >= CHUNK:
                full = await run_in_threadpool(_write_unless_full, sink, bytes(pending))
                pending.clear()
        if full is None:
            return await run_in_threadpool(sink.finish, bytes(pending))
        raise full
    except ClientDisconnect:
        raise BadParameter("the upload was interrupted before the end; send it again.") from None
    finally:
        sink.close()


def _write_unless_full(sink: _MultipartSink, data: bytes) -> OSError | None:
    """Write; on a full disk drop the partial file at once and return the error."""
    try:
        sink.write(data)
    except OSError as exc:
        if not is_disk_full(exc):
            raise
        sink.discard()
        return exc
    return None


def is_zip(path: Path) -> bool:
    with open(path, "rb") as f:
        head = f.read(4)
    return path.suffix.lower() == ".zip" or head in (b"PK\x03\x04", b"PK\x05\x06")


def _member_path(info: zipfile.ZipInfo) -> PurePosixPath | None:
    """The member's relative path, None for junk to skip; raises for unsafe members."""
    name = info.filename.replace("\\", "/")
    if not name:
        raise UnreadableVolume(
            "the zip holds a member without a name: its directory is damaged; create the zip again."
        )
    if name.startswith("/") or re.match(r"^[A-Za-z]:", name):
        raise UnsafeArchive(
            f"zip member {info.filename!r} has an absolute path; zip relative paths only."
        )
    parts = PurePosixPath(name).parts
    if ".." in parts:
        raise UnsafeArchive(
            f"zip member {info.filename!r} points outside the archive ('..'); "
            "zip the folder itself."
        )
    if info.create_system == 3 and stat.S_ISLNK(info.external_attr >> 16):
        raise UnsafeArchive(
            f"zip member {info.filename!r} is a symbolic link; zip real files only."
        )
    if info.is_dir() or not parts or parts[0] == "__MACOSX" or parts[-1].startswith("._"):
        return None
    return PurePosixPath(*parts)


def extract_zip(path: Path, dest: Path, max_bytes: int) -> None:
    """Unpack ``path`` into ``dest``, refusing unsafe members and more than ``max_bytes``."""
    try:
        with zipfile.ZipFile(path) as zf:
            infos = zf.infolist()
            if len(infos) > MAX_MEMBERS:
                raise UnsafeArchive(
                    f"the zip has {len(infos)} members; at most {MAX_MEMBERS} are accepted."
                )
            members = [(info, rel) for info in infos if (rel := _member_path(info)) is not None]
            if sum(info.file_size for info, _ in members) > max_bytes:
                raise UploadTooLarge(_too_large("unzipped content", max_bytes))
            _refuse_bombs([info for info, _ in members])
            total = 0
            for info, rel in members:
                total = _extract_member(zf, info, dest / rel, total, max_bytes)
    except (zipfile.BadZipFile, zlib.error, EOFError, UnicodeDecodeError) as exc:
        # UnicodeDecodeError: names flagged UTF-8 that are not (a damaged directory).
        raise UnreadableVolume(
            f"{path.name}: not a valid zip archive ({exc}); create the zip again."
        ) from None
    except (NotImplementedError, RuntimeError) as exc:  # unsupported compression, encryption
        raise UnreadableVolume(
            f"{path.name}: cannot unpack ({exc}); use a plain, unencrypted zip."
        ) from None


def _refuse_bombs(infos: list[zipfile.ZipInfo]) -> None:
    """Members that would inflate far beyond what scans compress to, refused from the
    declared sizes before anything is written (the DICOM reader's rule for zips)."""
    for info in infos:
        size, packed = info.file_size, max(info.compress_size, 1)
        if size > RATIO_FLOOR and size > MAX_ZIP_RATIO * packed:
            raise UnsafeArchive(
                f"zip member {info.filename!r} would inflate {packed} bytes to "
                f"{size / 2**20:.0f} MB ({size / packed:.0f}:1), far beyond what scans "
                "compress to (a zip bomb?); zip the slice files themselves again."
            )


def _extract_member(
    zf: zipfile.ZipFile, info: zipfile.ZipInfo, target: Path, total: int, limit: int
) -> int:
    """Copy one member, counting real decompressed bytes: the declared sizes can lie."""
    target.parent.mkdir(parents=True, exist_ok=True)
    with zf.open(info) as src, open(target, "wb") as out:
        while chunk := src.read(CHUNK):
            total += len(chunk)
            if total > limit:
                raise UploadTooLarge(_too_large("unzipped content", limit))
            out.write(chunk)
    return total


def volume_suffix(path: Path) -> str:
    name = path.name.lower()
    return next((s for s in VOLUME_SUFFIXES if name.endswith(s)), "")


def pick_source(folder: Path) -> Path:
    """What to read from an unpacked zip: its single volume file, else the folder (DICOM)."""
    files = [p for p in folder.rglob("*") if p.is_file()]
    if not files:
        raise UnreadableVolume(
            "the zip is empty; zip the folder of DICOM slices (or one volume file)."
        )
    singles = sorted(p for p in files if volume_suffix(p))
    if len(singles) > 1:
        names = ", ".join(str(p.relative_to(folder)) for p in singles[:5])
        raise BadParameter(f"the zip holds several volumes ({names}); upload one at a time.")
    return singles[0] if singles else folder
