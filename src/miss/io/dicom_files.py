"""Where DICOM files come from: a folder (recursively), a ``.zip`` or a single file.

Each source yields ``Entry`` objects whose ``fetch()`` gives something pydicom can
open, so the reader never cares whether a slice lives on disk or inside an archive.
Zip members are read into memory one at a time, never extracted, so a hostile member
name cannot write anywhere; names that try to climb out (``../``) or are absolute are
still refused, because an archive built like that is not one we should trust.
"""

from __future__ import annotations

import io
import re
import zipfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from miss.errors import UnreadableVolume

#: Refuse archives that would inflate beyond this (zip bombs); a 2000-slice CT is ~1 GB.
MAX_ZIP_BYTES = 8 * 1024**3
#: Files that are never slices: the DICOMDIR index, OS debris.
SKIP_NAMES = {"DICOMDIR", "Thumbs.db", ".DS_Store"}


@dataclass(frozen=True)
class Entry:
    """One candidate slice file; ``fetch()`` returns a path or an in-memory stream."""

    label: str
    fetch: Callable[[], str | BinaryIO]


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
    return [Entry(str(p.relative_to(folder)), _path_fetcher(p)) for p in files]


def _path_fetcher(path: Path) -> Callable[[], str]:
    return lambda: str(path)


def _skipped(name: str) -> bool:
    return name in SKIP_NAMES or name.startswith(".")


@contextmanager
def _open_zip(path: Path) -> Iterator[zipfile.ZipFile]:
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise UnreadableVolume(
            f"{path.name}: the zip archive is damaged ({exc}); create or download it again."
        ) from exc
    with archive:
        yield archive


def _zip_entries(path: Path, archive: zipfile.ZipFile) -> list[Entry]:
    members = [m for m in archive.infolist() if not m.is_dir()]
    for member in members:
        if _unsafe_member(member.filename):
            raise UnreadableVolume(
                f"{path.name}: refusing member {member.filename!r}, whose path leaves the "
                "archive (absolute or containing '..'); re-create the zip from the folder "
                "of slices with relative names."
            )
    total = sum(m.file_size for m in members)
    if total > MAX_ZIP_BYTES:
        raise UnreadableVolume(
            f"{path.name}: the archive would inflate to {total / 1024**3:.1f} GB, more than "
            f"the {MAX_ZIP_BYTES / 1024**3:.0f} GB limit; upload the series in parts."
        )
    kept = [m for m in members if not _skipped(PurePosixPath(m.filename).name)]
    kept = [m for m in kept if not m.filename.startswith("__MACOSX/")]
    return [Entry(m.filename, _member_fetcher(archive, m.filename)) for m in kept]


def _member_fetcher(archive: zipfile.ZipFile, name: str) -> Callable[[], BinaryIO]:
    return lambda: io.BytesIO(archive.read(name))


def _unsafe_member(name: str) -> bool:
    """True for absolute names (``/x``, ``\\x``, ``C:x``) and names with a ``..`` part."""
    parts = re.split(r"[\\/]", name)
    return name.startswith(("/", "\\")) or bool(re.match(r"^[A-Za-z]:", name)) or ".." in parts
