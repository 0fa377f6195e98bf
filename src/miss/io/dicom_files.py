"""Where DICOM files come from: a folder (recursively), a ``.zip`` or a single file.

Each source yields ``Entry`` objects whose ``fetch()`` gives something pydicom can
open, so the reader never cares whether a slice lives on disk or inside an archive.
Zip members are read into memory one at a time, never extracted, so a hostile member
name cannot write anywhere; names that try to climb out (``../``) or are absolute are
still refused, because an archive built like that is not one we should trust.
"""

from __future__ import annotations

import re
import stat
import zipfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO, cast

import pydicom
from pydicom.dataset import Dataset
from pydicom.errors import InvalidDicomError
from pydicom.uid import ExplicitVRBigEndian, ExplicitVRLittleEndian, ImplicitVRLittleEndian

from miss.errors import UnreadableVolume
from miss.io import codecs
from miss.io.archive import RATIO_FLOOR, ZIP_RATIO

#: Refuse archives that would inflate beyond this (zip bombs); a 2000-slice CT is ~1 GB.
MAX_ZIP_BYTES = 8 * 1024**3
#: Archives (and members) inflating more than ``MAX_ZIP_RATIO`` times their compressed size
#: once past ``RATIO_FLOOR`` bytes are refused: the upload's rule (``miss.io.archive``).
MAX_ZIP_RATIO = ZIP_RATIO
#: The first bytes of a data set without preamble: group 0008 (or 0002) little endian.
BARE_STARTS = (b"\x08\x00", b"\x02\x00")
#: Files that are never slices: the DICOMDIR index, OS debris.
SKIP_NAMES = {"DICOMDIR", "Thumbs.db", ".DS_Store"}


@dataclass(frozen=True)
class Entry:
    """One candidate slice file; ``fetch()`` returns a path or an in-memory stream."""

    label: str
    fetch: Callable[[], str | BinaryIO]


def read_dataset(entry: Entry, header_only: bool = False) -> Dataset:
    """pydicom's ``dcmread`` of one entry (up to the pixels when ``header_only``).

    Old files without the preamble and ``DICM`` (starting straight with group 0008) are
    read with ``force`` and given the transfer syntax pydicom found, so that their pixels
    decode too. Raises ``InvalidDicomError`` for anything else that is not DICOM.
    """
    try:
        with _opened(entry) as stream:
            codecs.check_deflated_dicom(Path(entry.label), stream)
            return pydicom.dcmread(stream, stop_before_pixels=header_only)
    except InvalidDicomError:
        with _opened(entry) as stream:
            if stream.read(2) not in BARE_STARTS:
                raise
            stream.seek(0)
            ds = pydicom.dcmread(stream, stop_before_pixels=header_only, force=True)
    if "TransferSyntaxUID" not in ds.file_meta and ds.original_encoding[0] is not None:
        implicit, little = ds.original_encoding
        ds.file_meta.TransferSyntaxUID = (
            ImplicitVRLittleEndian
            if implicit
            else ExplicitVRLittleEndian
            if little
            else ExplicitVRBigEndian
        )
    return ds


def number(ds: Dataset, keyword: str, default: float = 0.0) -> float:
    """A numeric header value, ``default`` when absent, empty or not a number."""
    try:
        value = ds.get(keyword, default)
        return default if value is None or value == "" else float(value)
    except (TypeError, ValueError):
        return default


@contextmanager
def _opened(entry: Entry) -> Iterator[BinaryIO]:
    source = entry.fetch()
    with open(source, "rb") if isinstance(source, str) else source as stream:
        yield stream


@contextmanager
def open_source(path: Path) -> Iterator[list[Entry]]:
    """Yield the candidate files of a folder, a zip archive or a single file.

    Raises
    ------
    UnreadableVolume
        For a damaged archive or one with unsafe member names.
    """
    if path.is_dir():
        yield _folder_entries(path)
    elif zipfile.is_zipfile(path):
        with _open_zip(path) as archive:
            yield _zip_entries(path, archive)
    elif path.suffix.lower() == ".zip":
        raise UnreadableVolume(
            f"{path.name}: not a valid zip archive (truncated or damaged); create or "
            "download it again."
        )
    else:
        yield [Entry(path.name, lambda: str(path))]


def _folder_entries(folder: Path) -> list[Entry]:
    files = sorted(p for p in folder.rglob("*") if p.is_file() and not _skipped(p.name))
    return [Entry(_printable(str(p.relative_to(folder))), _path_fetcher(p)) for p in files]


def _printable(name: str) -> str:
    """A file name as valid text: bytes that are not UTF-8 (kept by Python as lone
    surrogates) become U+FFFD, so messages naming the file can be encoded anywhere."""
    return name.encode("utf-8", "surrogateescape").decode("utf-8", "replace")


def _path_fetcher(path: Path) -> Callable[[], str]:
    return lambda: str(path)


def _skipped(name: str) -> bool:
    return name in SKIP_NAMES or name.startswith(".")


@contextmanager
def _open_zip(path: Path) -> Iterator[zipfile.ZipFile]:
    try:
        archive = zipfile.ZipFile(path)
    except UnicodeDecodeError as exc:
        raise UnreadableVolume(
            f"{path.name}: the zip archive says its member names are UTF-8 but they are not "
            "(the archive is damaged or was written by a faulty tool); create the zip again."
        ) from exc
    except Exception as exc:  # zipfile parses a hostile directory with IndexError and kin
        raise UnreadableVolume(
            f"{path.name}: the zip archive is damaged ({exc or type(exc).__name__}); create "
            "or download it again."
        ) from exc
    with archive:
        yield archive


def _zip_entries(path: Path, archive: zipfile.ZipFile) -> list[Entry]:
    if any(not m.filename for m in archive.infolist()):
        raise UnreadableVolume(
            f"{path.name}: the zip archive has a member without a name (it is damaged or "
            "was built by hand); create the zip again from the folder of slices."
        )
    members = [m for m in archive.infolist() if not m.is_dir()]
    for member in members:
        if _unsafe_member(member.filename):
            raise UnreadableVolume(
                f"{path.name}: refusing member {member.filename!r}, whose path leaves the "
                "archive (absolute or containing '..'); re-create the zip from the folder "
                "of slices with relative names."
            )
        if member.create_system == 3 and stat.S_ISLNK(member.external_attr >> 16):
            raise UnreadableVolume(
                f"{path.name}: refusing member {member.filename!r}, a symbolic link; "
                "re-create the zip from the slice files themselves (zip without --symlinks)."
            )
    _refuse_bomb(path, members)
    kept = [m for m in members if not _skipped(PurePosixPath(m.filename).name)]
    kept = [m for m in kept if not m.filename.startswith("__MACOSX/")]
    return [Entry(m.filename, _member_fetcher(archive, m.filename, path.name)) for m in kept]


def _refuse_bomb(path: Path, members: list[zipfile.ZipInfo]) -> None:
    """Refuse from the declared sizes, before inflating anything: too big, or too compressed."""
    total = sum(m.file_size for m in members)
    if total > MAX_ZIP_BYTES:
        raise UnreadableVolume(
            f"{path.name}: the archive would inflate to {total / 1024**3:.1f} GB, more than "
            f"the {MAX_ZIP_BYTES / 1024**3:.0f} GB limit; upload the series in parts."
        )
    packed = sum(m.compress_size for m in members)
    checks = [("the archive", total, packed)]
    checks += [(f"member {m.filename!r}", m.file_size, m.compress_size) for m in members]
    for what, size, compressed in checks:
        if size > RATIO_FLOOR and size > MAX_ZIP_RATIO * max(compressed, 1):
            raise UnreadableVolume(
                f"{path.name}: {what} would inflate {compressed} bytes to {size / 1024**2:.0f} MB "
                f"({size / max(compressed, 1):.0f}:1), far beyond what scans compress to (a zip "
                "bomb?); zip the slice files themselves again."
            )


def _member_fetcher(archive: zipfile.ZipFile, name: str, zip_name: str) -> Callable[[], BinaryIO]:
    """A stream that inflates the member as it is read (headers never inflate the pixels)."""

    def fetch() -> BinaryIO:
        try:
            return cast(BinaryIO, archive.open(name))  # typeshed says IO[bytes]: a binary file
        except (RuntimeError, NotImplementedError, zipfile.BadZipFile, ValueError) as exc:
            raise UnreadableVolume(
                f"{zip_name}: cannot open member {name!r} ({exc}); use a plain zip (deflated or "
                "stored, no password) of the slice files."
            ) from exc

    return fetch


def _unsafe_member(name: str) -> bool:
    r"""True for absolute names (``/x``, ``\x``, ``C:x``) and names with a ``..`` part."""
    parts = re.split(r"[\\/]", name)
    return name.startswith(("/", "\\")) or bool(re.match(r"^[A-Za-z]:", name)) or ".." in parts
