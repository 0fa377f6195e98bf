"""``miss backup DEST`` and ``miss restore SRC``: a consistent copy of a running server's
database and data folder, and a new data folder made from one.

A backup folder holds::

    manifest.json     when, which engine, the schema revision, and every file's size and
                      SHA-256 (restore checks each one)
    miss.sqlite3      the database, by SQLite's online backup API (one read transaction:
                      a consistent copy while the server writes), or
    database.dump     ``pg_dump --format=custom`` (one snapshot, likewise)
    files/            the data folder's volumes/ and models/ (not tmp/, not the lock)

The database is copied first, then the files. Stored volumes and finished models never
change and appear by rename, so a file copied later is the one the rows describe; a
folder made after the copy of the database is copied too and dropped at restore (no row
names it: ``Store.init``); a job running during the backup is queued again at restore.
A folder whose rows are in the copy but which was deleted before its files could be read
is named in the manifest under ``vanished``.

A backup holds the identity table: its folders are made 0700 and its files 0600, whatever
the umask. A restore believes nothing of the manifest it has not checked: before anything
is written, every file it names must be a plain relative path under ``volumes/`` or
``models/`` (no ``..``, no absolute or drive path, no backslash), ``database`` must be one
of the two names a backup uses, and each must be a regular file of the backup reached
through no symbolic link; else the whole restore is refused, naming the entry.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sqlite3
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

from sqlalchemy import create_engine, inspect, make_url, select

from miss import __version__
from miss.errors import BadParameter
from miss.server.storage import schema
from miss.server.storage.db import DONE, ModelRow, VolumeRow
from miss.server.storage.private import FILE_MODE, FOLDER_MODE, tighten
from miss.server.storage.store import PART, Store

MANIFEST = "manifest.json"
SQLITE_COPY = "miss.sqlite3"
PG_DUMP = "database.dump"
#: The parts of the data folder a backup holds.
FOLDERS = ("volumes", "models")
#: Files in those folders that are not data: a write cut short, a worker's log.
SKIPPED_SUFFIXES = (PART,)
CHUNK = 1 << 20


@dataclass(frozen=True)
class Summary:
    """What a backup or restore copied: files, their bytes, the database copy's bytes, and
    the seconds it took."""

    files: int
    bytes: int
    database_bytes: int
    seconds: float


def backup(data_dir: Path, database_url: str, dest: Path) -> Summary:
    """Copy the database, then the files, into the new or empty folder ``dest``."""
    start = time.monotonic()
    dest = Path(dest)
    _require_empty(dest, "backup into")
    tighten(dest, FOLDER_MODE, create=True)
    engine_name = _engine(database_url)
    if engine_name == "sqlite":
        database = dest / SQLITE_COPY
        _sqlite_backup(_sqlite_path(database_url), database)
        rows_url = f"sqlite:///{database}"
    else:
        database = dest / PG_DUMP
        _new_file(database).close()  # pg_dump keeps the mode of the file it overwrites
        _pg("pg_dump", database_url, "--format=custom", "--no-owner", f"--file={database}")
        rows_url = database_url  # the folders to copy: those the dump's rows name, or more
    volumes, models = _known_folders(rows_url)
    files: dict[str, dict[str, Any]] = {}
    for name in FOLDERS:
        _copy_tree(Path(data_dir) / name, dest / "files" / name, files)
    copied = {tuple(path.split("/")[:2]) for path in files}
    vanished = sorted(
        f"{folder}/{key}"
        for folder, keys in (("volumes", volumes), ("models", models))
        for key in keys
        if (folder, key) not in copied
    )
    manifest = {
        "miss": __version__,
        "made": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "engine": engine_name,
        "database": database.name,
        "database_sha256": _sha256(database),
        "schema": _revision(rows_url),
        "files": files,
        "vanished": vanished,
    }
    with _new_file(dest / MANIFEST) as out:
        out.write(json.dumps(manifest, indent=1, sort_keys=True).encode())
    return Summary(
        len(files),
        sum(f["bytes"] for f in files.values()),
        database.stat().st_size,
        time.monotonic() - start,
    )


def restore(src: Path, data_dir: Path, database_url: str) -> Summary:
    """Make the empty ``data_dir`` (and its empty database) from the backup ``src``."""
    start = time.monotonic()
    src, data_dir = Path(src), Path(data_dir)
    manifest = json.loads((src / MANIFEST).read_text())
    _check_manifest(src, manifest)
    _require_empty(data_dir, "restore into")
    engine_name = _engine(database_url)
    if manifest["engine"] != engine_name:
        raise BadParameter(
            f"this backup is of a {manifest['engine']} database and MISS_DATABASE_URL is "
            f"{engine_name}; restore it with the same engine."
        )
    database = src / manifest["database"]
    if _sha256(database) != manifest["database_sha256"]:
        raise BadParameter(f"{database} is not the file the backup made (checksum differs).")
    tighten(data_dir, FOLDER_MODE, create=True)
    if engine_name == "sqlite":
        _sqlite_backup(database, _sqlite_path(database_url))
    else:
        _require_empty_database(database_url)
        _pg("pg_restore", database_url, "--no-owner", "--exit-on-error", str(database))
    total = 0
    for relative, entry in sorted(manifest["files"].items()):
        target = data_dir / relative
        target.parent.mkdir(FOLDER_MODE, parents=True, exist_ok=True)
        digest = _copy_file(src / "files" / relative, target)
        if digest != entry["sha256"]:
            raise BadParameter(f"{src / 'files' / relative} differs from the backup's record.")
        total += entry["bytes"]
    store = Store(data_dir, database_url)
    try:
        store.init()  # a newer MISS: the schema upgraded; folders no row names dropped
    finally:
        store.close()
    return Summary(len(manifest["files"]), total, database.stat().st_size, time.monotonic() - start)


def _check_manifest(src: Path, manifest: Any) -> None:
    """Refuse the backup at ``src`` unless every path its ``manifest`` names is a regular
    file inside it: checked before anything is written (a crafted manifest must not make
    restore write, or read, anywhere else)."""
    files = manifest.get("files") if isinstance(manifest, dict) else None
    database = manifest.get("database") if isinstance(manifest, dict) else None
    if not isinstance(files, dict) or database not in (SQLITE_COPY, PG_DUMP):
        raise BadParameter(
            f"will not restore {src}: its {MANIFEST} names the database {database!r}, not "
            f"{SQLITE_COPY!r} or {PG_DUMP!r} (or lists no files); it was not made by "
            "'miss backup' or was altered."
        )
    _check_inside(src, database, src / database)
    for relative, entry in files.items():
        if not _plain_relative(relative) or not isinstance(entry, dict):
            raise _altered(src, relative)
        _check_inside(src, relative, src / "files" / relative)


def _plain_relative(name: Any) -> bool:
    """True for ``volumes/...`` or ``models/...`` in plain POSIX form: no ``..`` or ``.``,
    no absolute or drive path, no backslash, no empty part, no control character."""
    if not isinstance(name, str) or "\\" in name or not name.isprintable():
        return False
    parts = name.split("/")
    return (
        len(parts) >= 2
        and parts[0] in FOLDERS
        and not PurePosixPath(name).is_absolute()
        and all(part not in ("", ".", "..") and ":" not in part for part in parts)
    )


def _check_inside(src: Path, name: str, path: Path) -> None:
    """``path`` (named ``name`` in the manifest) must be a regular file of the backup
    reached through no symbolic link (a backup holds none)."""
    lexical = os.path.join(os.path.realpath(src), os.path.relpath(path, src))
    if os.path.realpath(path) != lexical or not path.is_file():
        raise _altered(src, name)


def _altered(src: Path, name: Any) -> BadParameter:
    return BadParameter(
        f"will not restore {src}: its {MANIFEST} names {name!r}, which is not a file inside "
        "the backup (a path out of it, or a symbolic link); it was altered. Nothing was "
        "restored."
    )


def _new_file(path: Path) -> Any:
    """``path`` opened for writing (binary, truncated), created 0600 whatever the umask."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, FILE_MODE)
    os.fchmod(fd, FILE_MODE)  # an existing file keeps its mode otherwise
    return os.fdopen(fd, "wb")


def _require_empty(folder: Path, what: str) -> None:
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise BadParameter(f"will not {what} {folder}: it is not an empty folder.")


def _require_empty_database(url: str) -> None:
    engine = create_engine(url)
    try:
        tables = inspect(engine).get_table_names()
    finally:
        engine.dispose()
    if tables:
        raise BadParameter(
            f"will not restore into a database that has tables ({', '.join(sorted(tables))}); "
            "create an empty one and point MISS_DATABASE_URL at it."
        )


def _engine(url: str) -> str:
    name = make_url(url).get_backend_name()
    if name not in ("sqlite", "postgresql"):
        raise BadParameter(f"backup and restore know SQLite and PostgreSQL, not {name}.")
    return name


def _sqlite_path(url: str) -> Path:
    database = make_url(url).database
    if not database or database == ":memory:":
        raise BadParameter(f"{url} is not a SQLite file.")
    return Path(database)


def _sqlite_backup(source: Path, target: Path) -> None:
    """SQLite's online backup: one consistent copy, whatever writes meanwhile."""
    target.parent.mkdir(FOLDER_MODE, parents=True, exist_ok=True)
    if not target.exists():
        _new_file(target).close()  # SQLite keeps the mode of the file it opens
    src = sqlite3.connect(f"file:{source}?mode=ro", uri=True, timeout=30)
    dst = sqlite3.connect(target)
    try:
        src.backup(dst)
    finally:
        dst.close()
        src.close()


def _pg(tool: str, url: str, *args: str) -> None:
    """Run ``pg_dump``/``pg_restore`` on the database of ``url`` (its password by the
    environment, never the command line, which every local user can read)."""
    parsed = make_url(url)
    env = {**os.environ}
    if parsed.password:
        env["PGPASSWORD"] = str(parsed.password)
    plain = parsed.set(drivername="postgresql", password=None).render_as_string()
    flag = "--dbname" if tool == "pg_restore" else ""
    target = [f"{flag}={plain}"] if flag else [plain]
    done = subprocess.run(
        [_pg_binary(tool), *args, *target], env=env, capture_output=True, text=True
    )
    if done.returncode != 0:
        raise BadParameter(f"{tool} failed: {done.stderr.strip()[-2000:]}")


def _pg_binary(tool: str) -> str:
    """The newest ``tool`` of Debian's PostgreSQL (a dump needs a pg_dump at least as new
    as the server), else the one on PATH."""
    found = sorted(
        Path("/usr/lib/postgresql").glob(f"*/bin/{tool}"), key=lambda p: int(p.parts[-3])
    )
    if found:
        return str(found[-1])
    on_path = shutil.which(tool)
    if on_path is None:
        raise BadParameter(f"{tool} not found; install PostgreSQL's client programs.")
    return on_path


def _known_folders(url: str) -> tuple[set[str], set[str]]:
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            volumes = set(conn.scalars(select(VolumeRow.id)))
            # Only a finished model has files for sure (a queued one has no folder yet).
            models = set(conn.scalars(select(ModelRow.id).where(ModelRow.status == DONE)))
    finally:
        engine.dispose()
    return volumes, models


def _revision(url: str) -> str | None:
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            return schema.current(conn)
    finally:
        engine.dispose()


def _copy_tree(source: Path, target: Path, files: dict[str, dict[str, Any]]) -> None:
    """Copy every data file under ``source``; a file gone meanwhile (deleted) is skipped."""
    base = source.parent
    for path in sorted(source.rglob("*")):
        if not path.is_file() or path.name.endswith(SKIPPED_SUFFIXES):
            continue
        relative = path.relative_to(base).as_posix()
        out = target.parent / relative
        out.parent.mkdir(FOLDER_MODE, parents=True, exist_ok=True)
        try:
            digest = _copy_file(path, out)
        except FileNotFoundError:
            continue
        files[relative] = {"bytes": out.stat().st_size, "sha256": digest}


def _copy_file(source: Path, target: Path) -> str:
    """Copy and hash in one read; flushed to disk. Returns the SHA-256 (hex)."""
    digest = hashlib.sha256()
    with open(source, "rb") as f, _new_file(target) as out:
        while chunk := f.read(CHUNK):
            digest.update(chunk)
            out.write(chunk)
        out.flush()
        os.fsync(out.fileno())
    return digest.hexdigest()


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK):
            digest.update(chunk)
    return digest.hexdigest()
