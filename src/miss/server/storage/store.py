"""Where everything lives: the database rows and the files under the data folder.

Layout of the data folder::

    miss.sqlite3              the database (unless MISS_DATABASE_URL points elsewhere); the
                              only place a patient's original identity is kept (its own table)
    volumes/<id>/data.zarr    voxels, real units (HU for CT), (X, Y, Z), a chunked Zarr
                              array with the affine and provenance as attributes
                              (``chunked``); ``data.npy`` before, migrated at start
    volumes/<id>/meta.json    affine, spacing, range, modality, series, presets (no patient data)
    volumes/<id>/labels.zarr, labels.json   a label map laid over it (``labelmaps``)
    volumes/<id>/histogram.json, thumbnail.png
    models/<id>/model.<fmt>   one file per output format: the GLB and model.mesh.npz (its
                              scene) by the job's worker, the others on their first
                              download (``formats``)
    models/<id>/worker.log    the worker's stderr, for the rare crash
    tmp/                      uploads and half-made volumes; emptied on start

Files appear by rename only (``tmp`` and ``volumes`` share a file system), so a reader
never sees half of one; they are flushed to disk (fsync) before the rename, so a crash
leaves either the old file or the whole new one. After a crash, ``Store.init`` empties
``tmp/``, drops ``volumes/`` and ``models/`` folders that have no database row, and the
``.part`` files of writes cut short.
"""

from __future__ import annotations

import fcntl
import json
import os
import secrets
import shutil
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np
from sqlalchemy import delete, func, select, update
from sqlalchemy.exc import IntegrityError

from miss.errors import is_disk_full
from miss.server.core.errors import DiskFull, NotFound
from miss.server.storage import chunked, schema
from miss.server.storage.appender import Appender
from miss.server.storage.bus import Bus
from miss.server.storage.caches import RowCache
from miss.server.storage.chunked import fsync_dir, sync_tree
from miss.server.storage.db import (
    DONE,
    FAILED,
    QUEUED,
    IdentityRow,
    ModelRow,
    SecretRow,
    VolumeRow,
    make_engine,
    make_sessionmaker,
)
from miss.server.storage.private import FOLDER_MODE, tighten
from miss.types import Volume

if TYPE_CHECKING:
    from miss.surface.blocks import ChunkCache


class DataDirInUse(RuntimeError):
    """Another MISS server already uses this data folder."""


#: Suffix of a file being written; ``Store.init`` removes the ones a crash left behind.
PART = ".part"
#: A running job's coarse first look at its model, in the model's folder.
PREVIEW_FILE = "preview.glb"
#: A large model's levels of detail (a 3D Tiles tileset), in the model's folder.
LOD_DIR = "lod"
#: A volume's voxels in its folder, and where they were before Zarr (``migrate``).
DATA, OLD_DATA = "data.zarr", "data.npy"
#: Volumes up to this many bytes are read whole by ``open_volume`` (``MISS_IN_MEMORY_MAX_MB``).
IN_MEMORY_MAX = 1 << 30
#: Bytes of decompressed chunks a server process keeps for slices (``Store.chunks``):
#: CThead's whole volume is 32 MB of them, a layer of a 512 x 512 CT's 32 MB.
CHUNK_CACHE = 128 << 20


def new_id() -> str:
    """A new random id: 16 hex digits."""
    return secrets.token_hex(8)


def write_atomic(path: Path, data: bytes) -> None:
    """Write beside ``path``, flush to disk and rename, so nobody reads a half-written
    file, not even after a crash; a full disk raises ``OSError`` and leaves nothing."""
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}{PART}")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        fsync_dir(path.parent)
    finally:
        tmp.unlink(missing_ok=True)


def remove_outputs(folder: Path) -> None:
    """Drop the model files of a failed run from its ``folder``: no half set stays, a full
    disk or an account's quota gets its room back (the worker's log stays)."""
    for path in (*folder.glob("model.*"), folder / PREVIEW_FILE, *folder.glob(f".*{PART}")):
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
    shutil.rmtree(folder / LOD_DIR, ignore_errors=True)


class Store:
    """Database rows and data-folder files of volumes and models."""

    def __init__(
        self,
        data_dir: Path,
        database_url: str,
        in_memory_max: int = IN_MEMORY_MAX,
        chunk_cache: int = 0,
    ) -> None:
        self.data_dir = Path(data_dir)
        self.in_memory_max = in_memory_max
        #: Decompressed chunks kept for lazy reads (a server's slices; ``chunk_cache``
        #: bytes, 0 for none: a job's worker reads each chunk once).
        self.chunks: ChunkCache | None = None
        if chunk_cache > 0:
            from miss.surface.blocks import ChunkCache

            self.chunks = ChunkCache(chunk_cache)
        self.database_url = database_url
        self.engine = make_engine(database_url)
        self.session = make_sessionmaker(self.engine)
        #: Sessions whose commits do not wait for the disk: for audit entries and job
        #: progress only (see ``db.make_engine``).
        self.light_engine = make_engine(database_url, durable=False)
        self.light_session = make_sessionmaker(self.light_engine)
        self.appender = Appender(self.light_session)
        #: Snapshots of volumes, finished models and login sessions (see ``caches``);
        #: what one process drops, the others of the same database drop too (``bus``).
        self.rows = RowCache()
        self.bus = Bus(self.engine, database_url)
        self.rows.on_change = self._publish_drop
        self.bus.subscribe("rows", self._hear_drop, on_gap=self.rows.clear_here)
        self._lock: IO[str] | None = None
        #: True while this process is the only server on the data folder (``lock``).
        self.alone = False

    # -- layout ---------------------------------------------------------------------------

    def volume_dir(self, volume_id: str) -> Path:
        """The volume's folder in the data folder (it may not exist)."""
        return self.data_dir / "volumes" / volume_id

    def model_dir(self, model_id: str) -> Path:
        """The model's folder in the data folder (it may not exist)."""
        return self.data_dir / "models" / model_id

    def tmp_dir(self) -> Path:
        """A fresh private folder under ``tmp/`` (same file system as the final places)."""
        path = self.data_dir / "tmp" / new_id()
        path.mkdir(parents=True)
        return path

    @property
    def shared(self) -> bool:
        """Several server processes may use this data folder: its database is PostgreSQL."""
        return self.bus.enabled

    def lock(self) -> None:
        """Take the data folder for this process; raises ``DataDirInUse`` if another has it.

        Starting sweeps ``tmp/`` and re-queues every running job: both are only safe when
        no other server is uploading into or running jobs from the same folder. On
        PostgreSQL several servers share the folder: the first takes it alone (``alone``)
        for its start, then shares it (``share``); one that starts beside others waits for
        any start under way and skips the sweeps.
        """
        # Owner-only also where no command set the umask (an app made in a test, a host).
        tighten(self.data_dir, FOLDER_MODE, create=True)
        handle = open(self.data_dir / "server.lock", "w")  # noqa: SIM115 - held until close()
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            self.alone = True
        except BlockingIOError:
            if not self.shared:
                handle.close()
                raise DataDirInUse(
                    f"another MISS server is using {self.data_dir}; stop it or choose another "
                    "--data-dir (several servers on one data folder need PostgreSQL)."
                ) from None
            fcntl.flock(handle, fcntl.LOCK_SH)  # after the start of the one that has it
        self._lock = handle

    def share(self) -> None:
        """Started: let other servers of the same database start beside this one."""
        if self.shared and self.alone and self._lock is not None:
            fcntl.flock(self._lock, fcntl.LOCK_SH)
            self.alone = False

    def init(self) -> None:
        """Lock the folder, create folders and tables, drop leftovers of an interrupted
        upload, job or delete (the server may have been killed at any point)."""
        self.lock()
        self.bus.hold_liveness()  # before this process claims a job (PostgreSQL)
        for sub in ("volumes", "models", "tmp"):
            (self.data_dir / sub).mkdir(parents=True, exist_ok=True)
        self.init_schema()
        if not self.alone:
            return  # the others' uploads and jobs are under way: leave their files be
        _empty(self.data_dir / "tmp")  # its contents only: tmp/ may be a mount point
        with self.session() as s:
            volumes = set(s.scalars(select(VolumeRow.id)))
            models = set(s.scalars(select(ModelRow.id)))
        # A volume moved into place whose row was never committed, a deleted model's folder.
        _remove_unknown(self.data_dir / "volumes", volumes)
        _remove_unknown(self.data_dir / "models", models)
        for folder in (self.data_dir / "volumes", self.data_dir / "models"):
            for part in folder.glob(f"*/.*{PART}"):  # write_atomic, write_planes cut short
                _remove_path(part)
        migrate(self.data_dir / "volumes")

    def free_bytes(self) -> int:
        """Free space on the data folder's disk for this (unprivileged) process, bytes."""
        stat = os.statvfs(self.data_dir)
        return stat.f_bavail * stat.f_frsize

    def check_free_space(self, min_free: int) -> None:
        """Refuse (507) new uploads and jobs while the data folder's disk has less than
        ``min_free`` bytes free: better a clear answer now than a full disk mid-write."""
        free = self.free_bytes()
        if free < min_free:
            raise DiskFull(
                f"disk full: only {free / 2**20:.0f} MB free in the server's data folder, "
                f"below its minimum of {min_free / 2**20:.0f} MB (MISS_MIN_FREE_MB); ask the "
                "administrator to free space there, then try again."
            )

    @contextmanager
    def disk_full_as_507(self) -> Iterator[None]:
        """Turn "no space left on device" inside the block into a 507 with a clear detail."""
        try:
            yield
        except OSError as exc:
            if not is_disk_full(exc):
                raise
            raise DiskFull(
                "disk full: the server's data folder ran out of space while storing this "
                "upload, and nothing of it was kept; ask the administrator to free space "
                "there, then send it again."
            ) from None

    def init_schema(self) -> None:
        """Bring the database to the newest schema (``schema.upgrade``: Alembic); safe beside
        a running server (``miss user``)."""
        if self.database_url.startswith("sqlite:///"):
            Path(self.database_url.removeprefix("sqlite:///")).parent.mkdir(
                parents=True, exist_ok=True
            )
        schema.upgrade(self.engine)

    def secret(self, name: str) -> bytes:
        """A server-wide random key, made on first use and kept in the database."""
        with self.session() as s:
            row = s.get(SecretRow, name)
        if row is None:
            try:
                with self.session.begin() as s:
                    s.add(SecretRow(name=name, value=secrets.token_hex(32)))
            except IntegrityError:  # made by another process meanwhile; use theirs
                pass
            with self.session() as s:
                row = s.get(SecretRow, name)
        assert row is not None
        return bytes.fromhex(row.value)

    def _publish_drop(self, keys: tuple[Any, ...] | None) -> None:
        if keys is None:
            self.bus.publish("rows", None)
            return
        keys = tuple(keys)
        for start in range(0, len(keys), 100):  # NOTIFY's payload is under 8000 bytes
            self.bus.publish("rows", [list(k) for k in keys[start : start + 100]])

    def _hear_drop(self, keys: list[list[str]] | None) -> None:
        if keys is None:
            self.rows.clear_here()
        else:
            self.rows.drop_here(*(tuple(k) for k in keys))

    def close(self) -> None:
        """Stop the bus and the appender, close the database connections and release the
        data folder's lock."""
        self.bus.stop()
        self.appender.stop()
        self.engine.dispose()
        self.light_engine.dispose()
        if self._lock is not None:
            self._lock.close()
            self._lock = None

    # -- volumes --------------------------------------------------------------------------

    def list_volumes(
        self, owner_id: str | None = None, newest_first: bool = False
    ) -> list[VolumeRow]:
        """Every volume, or only those of ``owner_id``; oldest first, or ``newest_first``
        (the id breaks ties between volumes stored within the clock's resolution)."""
        if newest_first:
            query = select(VolumeRow).order_by(VolumeRow.created_at.desc(), VolumeRow.id.desc())
        else:
            query = select(VolumeRow).order_by(VolumeRow.created_at, VolumeRow.id)
        if owner_id is not None:
            query = query.where(VolumeRow.owner_id == owner_id)
        with self.session() as s:
            return list(s.scalars(query))

    def count_volumes(self) -> int:
        """How many volumes are stored."""
        with self.session() as s:
            return s.scalar(select(func.count()).select_from(VolumeRow)) or 0

    def get_volume(self, volume_id: str) -> VolumeRow:
        """The volume's row (a snapshot: volumes change only by being deleted)."""
        row = self.rows.cached(
            ("volume", volume_id), lambda: self._get(VolumeRow, volume_id), always
        )
        if row is None:
            raise NotFound(f"no volume {volume_id!r}; GET /api/volumes lists the volumes.")
        return row

    def cached_volume(self, volume_id: str) -> VolumeRow | None:
        """The volume's row if this process holds it, else None; never waits (the event
        loop asks this before it decides to hand a request to the threadpool)."""
        return self.rows.get(("volume", volume_id))

    def add_volume(
        self,
        staged: Path,
        name: str,
        slug: str,
        info: dict[str, Any],
        owner_id: str | None = None,
        identity: dict[str, Any] | None = None,
    ) -> VolumeRow:
        """Move a staged folder (data.npy, meta.json ...) into place and record it; the
        original patient identity, if kept, goes to its own owner-only row."""
        row = VolumeRow(id=new_id(), name=name, slug=slug, info=info, owner_id=owner_id)
        final = self.volume_dir(row.id)
        sync_tree(staged)  # the files on disk before the row that says they are there
        os.replace(staged, final)
        fsync_dir(final.parent)
        try:
            with self.session.begin() as s:
                s.add(row)
                if identity:
                    s.flush()  # the volume before the row that refers to it
                    s.add(IdentityRow(volume_id=row.id, owner_id=owner_id, data=identity))
        except BaseException:
            shutil.rmtree(final, ignore_errors=True)
            raise
        return row

    def delete_volume(self, volume_id: str) -> list[str]:
        """Delete a volume, its models and their files; returns the deleted model ids."""
        self.get_volume(volume_id)
        with self.session.begin() as s:
            model_ids = list(s.scalars(select(ModelRow.id).where(ModelRow.volume_id == volume_id)))
            s.execute(delete(ModelRow).where(ModelRow.volume_id == volume_id))
            s.execute(delete(VolumeRow).where(VolumeRow.id == volume_id))
        self.rows.drop(("volume", volume_id), *(("model", m) for m in model_ids))
        for model_id in model_ids:
            _remove_tree(self.model_dir(model_id), self.data_dir)
        _remove_tree(self.volume_dir(volume_id), self.data_dir)
        if self.chunks is not None:
            gone = str(self.volume_dir(volume_id) / DATA) + os.sep
            self.chunks.drop(lambda key: key[0].startswith(gone))
        return model_ids

    def open_volume(self, volume_id: str, lazy: bool = False) -> Volume:
        """The stored volume (no DICOM parsing): its voxels read whole and read-only up to
        ``in_memory_max`` bytes, else (or when ``lazy``: a slice, a region) a lazy
        ``zarr.Array`` that reads only the chunks asked for."""
        folder = self.volume_dir(volume_id)
        meta = json.loads((folder / "meta.json").read_text())
        data = self.voxels(folder / DATA, folder / OLD_DATA, lazy)
        return Volume(data=data, affine=np.array(meta["affine"]), meta=meta, patient={})

    def voxels(self, path: Path, old: Path, lazy: bool = False) -> Any:
        """The array at ``path`` (``chunked``), whole when small enough and not ``lazy``;
        ``old``, a .npy memory-mapped, while another server has not migrated it yet."""
        if not path.exists() and old.exists():
            return np.load(old, mmap_mode="r")
        if lazy:
            return chunked.read(path, -1, self.chunks)
        return chunked.read(path, self.in_memory_max)

    def read_json(self, volume_id: str, name: str) -> Any:
        """The JSON file ``name`` stored with the volume."""
        return json.loads((self.volume_dir(volume_id) / name).read_text())

    # -- models ---------------------------------------------------------------------------

    def get_model(self, model_id: str) -> ModelRow:
        """The model's row; a finished one is a snapshot (it changes only by being
        deleted), a queued or running one is read afresh (its worker writes it)."""
        row = self.rows.cached(("model", model_id), lambda: self._get(ModelRow, model_id), done)
        if row is None:
            raise NotFound(f"no model {model_id!r}; GET /api/models lists the models.")
        return row

    def cached_model(self, model_id: str) -> ModelRow | None:
        """A finished model's row if this process holds it, else None; never waits."""
        return self.rows.get(("model", model_id))

    def get_identity(self, volume_id: str) -> IdentityRow | None:
        """The original patient identity kept for the volume (owner only), or None."""
        with self.session() as s:
            return s.get(IdentityRow, volume_id)

    def list_models(
        self, volume_id: str | None = None, owner_id: str | None = None
    ) -> list[ModelRow]:
        """Models of one volume, or of the volumes of ``owner_id``, or all."""
        query = select(ModelRow).order_by(ModelRow.created_at)
        if volume_id is not None:
            query = query.where(ModelRow.volume_id == volume_id)
        if owner_id is not None:
            owned = select(VolumeRow.id).where(VolumeRow.owner_id == owner_id)
            query = query.where(ModelRow.volume_id.in_(owned))
        with self.session() as s:
            return list(s.scalars(query))

    def models_submitted_by(self, account: str) -> list[str]:
        """Ids of the models ``account`` (a user name) queued last."""
        query = select(ModelRow.id).where(ModelRow.submitted_by == account)
        with self.session() as s:
            return list(s.scalars(query))

    def find_or_create_model(
        self, volume_id: str, key: str, spec: dict[str, Any], submitted_by: str | None = None
    ) -> tuple[ModelRow, bool]:
        """The model with these parameters on this volume, created (queued) if new.

        A failed one is queued again: the failure may have been a crash or a restart.
        ``submitted_by`` (an account name) is recorded when a job is queued.
        """
        existing = self.find_model(volume_id, key)
        if existing is None:
            row = ModelRow(
                id=new_id(),
                volume_id=volume_id,
                key=key,
                spec=spec,
                status=QUEUED,
                submitted_by=submitted_by,
            )
            try:
                with self.session.begin() as s:
                    s.add(row)
                return row, True
            except IntegrityError:  # the same request raced us; theirs wins
                existing = self.find_model(volume_id, key)
                assert existing is not None
        if existing.status == FAILED:
            self.update_model(
                existing.id,
                status=QUEUED,
                progress=0.0,
                stage="",
                error=None,
                attempts=0,
                submitted_by=submitted_by,
            )
            return self.get_model(existing.id), True
        return existing, False

    def find_model(self, volume_id: str, key: str) -> ModelRow | None:
        """The model of ``volume_id`` made with parameters ``key``, if any."""
        query = select(ModelRow).where(ModelRow.volume_id == volume_id, ModelRow.key == key)
        with self.session() as s:
            return s.scalars(query).first()

    def delete_model(self, model_id: str) -> None:
        """Delete the model's row and folder; NotFound (404) when there is no such model."""
        self.get_model(model_id)
        with self.session.begin() as s:
            s.execute(delete(ModelRow).where(ModelRow.id == model_id))
        self.rows.drop(("model", model_id))
        _remove_tree(self.model_dir(model_id), self.data_dir)

    def update_model(
        self, model_id: str, *conditions: Any, durable: bool = True, **values: Any
    ) -> bool:
        """Update one model row if ``conditions`` hold; True when a row changed.
        ``durable=False`` for progress (``db.make_engine``)."""
        query = update(ModelRow).where(ModelRow.id == model_id, *conditions).values(**values)
        with (self.session if durable else self.light_session).begin() as s:
            changed = s.execute(query).rowcount == 1
        self.rows.drop(("model", model_id))  # after the commit: see RowCache.generation
        return changed

    def _get(self, table: type[Any], key: str) -> Any:
        with self.session() as s:
            return s.get(table, key)


def always(_row: Any) -> bool:
    """Keep every cached row (``RowCache.cached``'s ``keep``)."""
    return True


def done(row: ModelRow) -> bool:
    """Keep a cached model row only once its job is done."""
    return row.status == DONE


def _remove_tree(path: Path, data_dir: Path) -> None:
    """Remove by first renaming into ``tmp/`` so a crash mid-delete leaves no half folder."""
    if not path.exists():
        return
    trash = data_dir / "tmp" / f"trash-{new_id()}"
    os.replace(path, trash)
    shutil.rmtree(trash, ignore_errors=True)


def _remove_unknown(parent: Path, known: set[str] | Sequence[str]) -> None:
    for child in parent.iterdir():
        if child.name not in known:
            _remove_path(child)


def _empty(folder: Path) -> None:
    for child in folder.iterdir():
        _remove_path(child)


def _remove_path(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def migrate(volumes: Path) -> None:
    """Store the ``.npy`` voxels of an older MISS as Zarr (``chunked``): each written
    beside its .npy, read back and compared, and only then the .npy removed. A crash
    anywhere leaves the .npy, and the next start does it again."""
    for old in sorted(volumes.glob("*/*.npy")):
        new = old.with_suffix(".zarr")
        data = np.load(old, mmap_mode="r")
        # labels.npy has its affine in labels.json; without one it was never finished
        described = old.parent / ("meta.json" if old.name == OLD_DATA else "labels.json")
        if not described.exists():
            old.unlink()
            continue
        affine = json.loads(described.read_text())["affine"]
        _remove_path(new)  # a migration cut short after the rename: done again
        chunked.write_array(new, data, {"affine": affine, "provenance": {"migrated": old.name}})
        if not chunked.same_voxels(new, data):
            _remove_path(new)
            raise RuntimeError(
                f"{new}: the Zarr copy of {old.name} differs from it; {old.name} is kept. "
                "Check the disk (dmesg), then start the server again."
            )
        del data
        old.unlink()
        fsync_dir(old.parent)
