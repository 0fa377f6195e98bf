"""Owner-only files: the data folder, the database and backups are MISS's account's alone.

The data folder holds the identity table (patients' names) and every volume, so nothing
MISS writes may be readable by another local account, whatever umask the shell that
started it had (022, the usual one, makes files world-readable). Every command that
writes there (``miss serve``, ``ingest``, ``backup``, ``restore``, ``user``) starts with
:func:`owner_only`: the process umask becomes 077, which the job workers and every file
and folder made later inherit (SQLite's -wal/-shm/-journal files take the database
file's mode), and an existing data folder or SQLite file that others could read is
tightened, which the command says on stderr.
"""

from __future__ import annotations

import os
import stat
import sys
from pathlib import Path

from sqlalchemy import make_url

#: New files 0600, new folders 0700.
UMASK = 0o077
FOLDER_MODE = 0o700
FILE_MODE = 0o600
#: SQLite's files beside the database.
SQLITE_SIDES = ("", "-wal", "-shm", "-journal")


def owner_only(data_dir: Path, database_url: str = "") -> list[Path]:
    """Set the process umask to 077, make ``data_dir`` (created if missing) 0700 and the
    SQLite database files of ``database_url`` 0600; returns the paths that were open to
    others and are not any more (each said on stderr)."""
    os.umask(UMASK)
    tightened = [p for p in (Path(data_dir),) if tighten(p, FOLDER_MODE, create=True)]
    database = _sqlite_file(database_url)
    if database is not None:
        for side in SQLITE_SIDES:
            path = database.with_name(database.name + side)
            if tighten(path, FILE_MODE):
                tightened.append(path)
    for path in tightened:
        print(
            f"miss: {path} was readable by other accounts; made it owner-only "
            f"({stat.S_IMODE(path.stat().st_mode):o})",
            file=sys.stderr,
        )
    return tightened


def tighten(path: Path, mode: int, create: bool = False) -> bool:
    """Take the group and other bits off ``path`` (a folder made with ``mode`` when
    ``create`` and missing); True when it had any. A missing path is left alone."""
    if create:
        path.mkdir(mode=mode, parents=True, exist_ok=True)
    try:
        was = stat.S_IMODE(path.stat().st_mode)
    except FileNotFoundError:
        return False
    if not was & 0o077:
        return False
    path.chmod(was & ~0o077)
    return True


def _sqlite_file(url: str) -> Path | None:
    if not url.startswith("sqlite"):
        return None
    database = make_url(url).database
    if not database or database == ":memory:":
        return None
    return Path(database)
