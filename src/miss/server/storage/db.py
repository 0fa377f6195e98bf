"""Database tables (SQLAlchemy 2): volumes and models (the jobs that make them), users and
their sessions, the owner-only identity records, share links and who opened them, the
audit log and the consultation rooms' events.

Voxel arrays and model files live on disk under the data folder; the database holds
what lists, looks up and survives a restart: names, sizes, job state and statistics.
Patient identity lives in one table only (``identities``), never beside the volume.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    Engine,
    ForeignKey,
    String,
    Text,
    UniqueConstraint,
    create_engine,
    event,
    false,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, sessionmaker

#: Job states, in the order a job passes through them.
QUEUED, RUNNING, DONE, FAILED = "queued", "running", "done", "failed"


def utcnow() -> datetime:
    """Now in UTC without a time zone, as the database columns keep times."""
    return datetime.now(UTC).replace(tzinfo=None)


class Base(DeclarativeBase):
    """The tables' base: dicts and lists are stored as JSON."""

    type_annotation_map = {dict[str, Any]: JSON, list[Any]: JSON}


class UserRow(Base):
    """An account; ``password`` is an argon2 hash (the PHC string, salt included)."""

    __tablename__ = "users"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    password: Mapped[str] = mapped_column(String(200))
    is_admin: Mapped[bool] = mapped_column(default=False)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    disabled: Mapped[bool] = mapped_column(default=False)
    #: May search the PACS, import from it and send models to it (an administrator grants).
    pacs: Mapped[bool] = mapped_column(default=False)


class SessionRow(Base):
    """A login: ``id`` is the SHA-256 of the bearer token, so a leaked database holds no
    usable token; ``csrf`` is the value cookie-authenticated writes must echo."""

    __tablename__ = "sessions"

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    user_id: Mapped[str] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    csrf: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    expires_at: Mapped[datetime] = mapped_column(index=True)


class VolumeRow(Base):
    """An uploaded (or demo) volume; its voxels are in ``volumes/<id>/data.zarr``."""

    __tablename__ = "volumes"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    owner_id: Mapped[str | None] = mapped_column(
        ForeignKey("users.id", ondelete="SET NULL"), index=True, default=None
    )
    name: Mapped[str] = mapped_column(String(200))
    slug: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    info: Mapped[dict[str, Any]] = mapped_column(default=dict)


class ModelRow(Base):
    """A surface model of a volume and the job that computes it.

    ``key`` is ``JobSpec.key()``: identical parameters on one volume share one row.
    """

    __tablename__ = "models"
    __table_args__ = (UniqueConstraint("volume_id", "key", name="uq_model_volume_key"),)

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    volume_id: Mapped[str] = mapped_column(ForeignKey("volumes.id", ondelete="CASCADE"), index=True)
    key: Mapped[str] = mapped_column(String(64))
    spec: Mapped[dict[str, Any]] = mapped_column(default=dict)
    status: Mapped[str] = mapped_column(String(16), default=QUEUED, index=True)
    progress: Mapped[float] = mapped_column(default=0.0)
    stage: Mapped[str] = mapped_column(String(32), default="")
    stats: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)
    files: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)
    error: Mapped[str | None] = mapped_column(Text, default=None)
    attempts: Mapped[int] = mapped_column(default=0)
    pid: Mapped[int | None] = mapped_column(default=None)
    #: The account that last queued the job (the per-account job limit counts these).
    submitted_by: Mapped[str | None] = mapped_column(String(64), default=None)
    #: The server process running the job (its ``Bus.origin``): when that process is gone
    #: (PostgreSQL: its liveness lock is free) another one queues the job again.
    runner: Mapped[str | None] = mapped_column(String(32), default=None)
    #: The display name its owner gave it (None: named after its parameters).
    name: Mapped[str | None] = mapped_column(String(200), default=None)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(default=None)
    finished_at: Mapped[datetime | None] = mapped_column(default=None)
    updated_at: Mapped[datetime] = mapped_column(default=utcnow, onupdate=utcnow)


class IdentityRow(Base):
    """The original patient identity of a volume and its UID mapping, for its owner only.

    Kept out of ``volumes.info`` and the data folder on purpose: everything else may be
    shared, this row never is.
    """

    __tablename__ = "identities"

    volume_id: Mapped[str] = mapped_column(
        ForeignKey("volumes.id", ondelete="CASCADE"), primary_key=True
    )
    owner_id: Mapped[str | None] = mapped_column(String(32), default=None)
    data: Mapped[dict[str, Any]] = mapped_column(default=dict)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class ShareRow(Base):
    """A share link to a model, or to a volume with its models. ``token_hash`` is the
    SHA-256 of the link's token: the token itself is shown once, at creation."""

    __tablename__ = "shares"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    owner_id: Mapped[str] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    model_id: Mapped[str | None] = mapped_column(
        ForeignKey("models.id", ondelete="CASCADE"), index=True, default=None
    )
    volume_id: Mapped[str | None] = mapped_column(
        ForeignKey("volumes.id", ondelete="CASCADE"), index=True, default=None
    )
    label: Mapped[str] = mapped_column(String(200), default="")  # the owner's own note
    message: Mapped[str] = mapped_column(String(1000), default="")  # what guests read
    can_download: Mapped[bool] = mapped_column(default=False)
    can_annotate: Mapped[bool] = mapped_column(default=False)
    # the scan itself (its de-identified voxels) in the guest's 3-D view (issue 43)
    can_view_volume: Mapped[bool] = mapped_column(default=False, server_default=false())
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    expires_at: Mapped[datetime] = mapped_column()
    revoked_at: Mapped[datetime | None] = mapped_column(default=None)


class ShareOpeningRow(Base):
    """A signed-in user (not its owner) opened a share link: when last. The library's
    "Shared with me" lists these; a guest without an account leaves none."""

    __tablename__ = "share_openings"

    share_id: Mapped[str] = mapped_column(
        ForeignKey("shares.id", ondelete="CASCADE"), primary_key=True
    )
    user_id: Mapped[str] = mapped_column(
        ForeignKey("users.id", ondelete="CASCADE"), primary_key=True, index=True
    )
    opened_at: Mapped[datetime] = mapped_column(default=utcnow)


class AuditRow(Base):
    """Who did what, when, from where. ``actor`` is a user name or ``link:<share id>``."""

    __tablename__ = "audit"

    id: Mapped[int] = mapped_column(primary_key=True, autoincrement=True)
    at: Mapped[datetime] = mapped_column(default=utcnow, index=True)
    actor: Mapped[str] = mapped_column(String(80))
    action: Mapped[str] = mapped_column(String(32), index=True)
    target: Mapped[str] = mapped_column(String(80), default="")
    address: Mapped[str] = mapped_column(String(64), default="")
    detail: Mapped[dict[str, Any]] = mapped_column(default=dict)


class RoomEventRow(Base):
    """One thing that happened in a model's consultation room (pin, measurement, chat,
    join, presenter ...). Pins and measurements are rebuilt from these rows, so the room's
    state and its replay come from the same record. ``session`` numbers the periods
    during which the room had anyone in it."""

    __tablename__ = "room_events"

    id: Mapped[int] = mapped_column(primary_key=True, autoincrement=True)
    model_id: Mapped[str] = mapped_column(ForeignKey("models.id", ondelete="CASCADE"), index=True)
    session: Mapped[int] = mapped_column(default=1)
    at: Mapped[datetime] = mapped_column(default=utcnow)
    kind: Mapped[str] = mapped_column(String(16))
    author: Mapped[str] = mapped_column(String(80), default="")
    data: Mapped[dict[str, Any]] = mapped_column(default=dict)


class PacsImportRow(Base):
    """A series being brought in from a PACS, for its owner only: the PACS's name and the
    original study and series UIDs (identity, like the ``identities`` table), the job's
    state, and the volume it became."""

    __tablename__ = "pacs_imports"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    owner_id: Mapped[str] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    pacs: Mapped[str] = mapped_column(String(64))
    study: Mapped[str] = mapped_column(String(64))
    series: Mapped[str] = mapped_column(String(64))
    segmentation: Mapped[str] = mapped_column(String(64), default="auto")
    name: Mapped[str] = mapped_column(String(200), default="")
    status: Mapped[str] = mapped_column(String(16), default=QUEUED, index=True)
    stage: Mapped[str] = mapped_column(String(64), default="")
    progress: Mapped[float] = mapped_column(default=0.0)
    volume_id: Mapped[str | None] = mapped_column(
        ForeignKey("volumes.id", ondelete="SET NULL"), default=None
    )
    labels: Mapped[int] = mapped_column(default=0)
    error: Mapped[str | None] = mapped_column(Text, default=None)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    finished_at: Mapped[datetime | None] = mapped_column(default=None)


class SecretRow(Base):
    """Server-wide random keys made on first use (the UID remapping key)."""

    __tablename__ = "secrets"

    name: Mapped[str] = mapped_column(String(32), primary_key=True)
    value: Mapped[str] = mapped_column(String(128))


#: Columns added after a table first shipped, before MISS kept its schema with Alembic:
#: (table, column, SQL type). A database from then may lack some; ``schema.upgrade`` adds
#: them before it stamps the database with the first revision. New columns are revisions.
ADDED_COLUMNS = (
    ("volumes", "owner_id", "VARCHAR(32)"),
    ("models", "submitted_by", "VARCHAR(64)"),
    ("users", "disabled", "BOOLEAN NOT NULL DEFAULT FALSE"),
    ("shares", "message", "VARCHAR(1000) NOT NULL DEFAULT ''"),
    ("users", "pacs", "BOOLEAN NOT NULL DEFAULT FALSE"),
)


#: SQLite connections kept open per process (starlette's threadpool has 40 threads).
POOL_SIZE = 40


def make_engine(url: str, durable: bool = True) -> Engine:
    """An engine; SQLite gets WAL and a busy timeout because worker processes write too.

    ``synchronous=FULL`` (``durable``): each commit is on disk (the WAL fsynced) before it
    returns, so what the server has acknowledged (a share link shown once, a finished
    model, a pin) survives a power cut as well as a killed process. It costs one fsync
    per commit, and the database's write lock is held meanwhile: while an upload is
    flushed to disk that fsync can take a second.

    ``durable=False`` (``synchronous=NORMAL``) is for the frequent small records nobody
    is told are saved: audit entries and job progress. Their commits are in the WAL
    before they return, so they survive a killed server; a power cut may lose the last
    of them, never the database's consistency. The next durable commit, or a checkpoint,
    puts them on disk too.
    """
    if not url.startswith("sqlite"):
        return create_engine(url, pool_pre_ping=True)
    # An overflow connection is closed on return and the next one pays the connect and
    # the pragmas again, so the pool keeps one for each thread that may ask at once.
    engine = create_engine(
        url,
        connect_args={"check_same_thread": False, "timeout": 30},
        pool_size=POOL_SIZE,
        max_overflow=8,
    )
    synchronous = "FULL" if durable else "NORMAL"

    @event.listens_for(engine, "connect")
    def _sqlite_pragmas(dbapi_conn: Any, _record: Any) -> None:
        cur = dbapi_conn.cursor()
        cur.execute("PRAGMA journal_mode=WAL")
        cur.execute(f"PRAGMA synchronous={synchronous}")
        cur.execute("PRAGMA busy_timeout=30000")
        cur.execute("PRAGMA foreign_keys=ON")
        # Deleted rows (an identity record, a revoked link) are overwritten, not left in
        # free pages of the file.
        cur.execute("PRAGMA secure_delete=ON")
        cur.close()

    return engine


def make_sessionmaker(engine: Engine) -> sessionmaker:
    """Sessions whose rows stay readable after commit (they are not expired)."""
    # Rows leave the session as plain snapshots: routes read them after commit.
    return sessionmaker(engine, expire_on_commit=False)
