"""The server's one ``Settings`` object, read from the environment in one place.

Environment variables (all optional):

``MISS_DATA_DIR``         folder for the database, volumes and models (``./miss-data``)
``MISS_DATABASE_URL``     SQLAlchemy URL (SQLite file in the data folder; PostgreSQL with
                          ``miss[postgres]``, needed for several server processes)
``MISS_METRICS_TOKEN``    bearer token ``/metrics`` accepts besides administrators
                          (read by ``miss.server.metrics.registry``; none by default)
``MISS_MAX_UPLOAD_MB``    largest accepted upload, MB (2048)
``MISS_MAX_UNZIPPED_MB``  largest total size a zip may expand to, MB (4 x the upload limit)
``MISS_WORKERS``          jobs run at the same time, each in its own process (1)
``MISS_DEMO``             register the demo phantom on first start ("1"; "0" to skip)
``MISS_HOST``, ``MISS_PORT``  where ``miss serve`` listens (127.0.0.1, 8000)
``MISS_ADMIN_PASSWORD``   password of the ``admin`` account made on first start (random,
                          printed once, when unset)
``MISS_SESSION_HOURS``    how long a login lasts, hours (12)
``MISS_MAX_JOBS_PER_USER`` jobs one account may have queued or running at once (2)
``MISS_API_RATE``         sustained API requests per second per account or address (20)
``MISS_API_BURST``        API requests allowed at once before the rate applies (200)
``MISS_MIN_FREE_MB``      uploads and jobs are refused while the data folder's disk has
                          less free space than this, MB (256)
``MISS_WORKER_MEMORY_MB`` memory one job's worker may use beyond its code and the volume,
                          MB (physical memory; 0: no cap; see ``miss.server.jobs.worker``)
``MISS_IN_MEMORY_MAX_MB`` volumes up to this size (decompressed) are read whole into memory
                          for a job or a slice; larger ones are read chunk by chunk as
                          needed, MB (1024)
``MISS_PARSE_SECONDS``    longest an upload's confined reader may run, seconds (600)
``MISS_PARSE_MEMORY_MB``  memory an upload's confined reader may use beyond its libraries,
                          MB (4096: a 1 GiB volume read whole fits; 0: no cap); compressed
                          files may decode to at most ``MISS_MAX_UNZIPPED_MB``, and past 64 MB
                          to 100 times their size (``miss.io.codecs``)
``MISS_UPLOADS_PER_USER`` uploads one account may send at once (2); more get 429
``MISS_UPLOADS_AT_ONCE``  uploads the server receives at once from everyone (4)
``MISS_PACS_URL``         DICOMweb root of the hospital's PACS (none); ``MISS_PACS_NAME``,
                          ``MISS_PACS_AUTH_FILE``, ``MISS_PACS_TIMEOUT`` and more PACS as
                          ``MISS_PACS2_URL`` ...: see ``miss.pacs.server``
``MISS_PACS_IMPORTS``     PACS series imported at once (2; one account at most all but one)
``MISS_PACS_IMPORTS_PER_USER`` PACS imports one account may have queued or running (10);
                          more get 429
``MISS_PACS_SEND_UPLOADS`` send a model of an uploaded (not PACS-imported) volume to the
                          PACS as a new study under the file's patient ("0": refused, 409)
``MISS_ROOM_MAX_PEOPLE``  people in one model's consultation room at once, counted over
                          every server process (50)
``MISS_UPLOAD_MIN_KBPS``  an upload's body must arrive at this average rate, kB/s, over each
                          ``MISS_UPLOAD_RATE_SECONDS`` (30) after the first; slower, or
                          ``MISS_UPLOAD_IDLE_SECONDS`` (60) without a byte: 408, slot freed (8)
``MISS_ROOM_RESERVED``    places of a room kept for the owner and administrators: guests fill
                          at most ``MISS_ROOM_MAX_PEOPLE`` less these (5; fewer in a room
                          of 5 or fewer places)
``MISS_ROOM_GUESTS_PER_LINK`` guests in one room through one share link at once (20)
``MISS_SSE_PER_USER``     event streams (``/api/models/{id}/events``) one account or client
                          address may hold open at once (10); more get 429
``MISS_WS_CONNECTS_PER_MINUTE`` WebSocket connections one client address may open a minute,
                          all at once at most (60); more are closed with 4429
``MISS_LOD_TRIANGLES``    a model of more triangles also gets levels of detail (a 3D Tiles
                          tileset the viewer refines as it zooms in); 2,000,000; 0: never
``MISS_WORKERS_PER_ACCOUNT`` jobs of one account run at once (``MISS_WORKERS`` less one, at
                          least 1): the last worker is kept for another account's job
``MISS_JOB_CPU_SECONDS``  CPU time one job's worker may use, seconds, all its threads
                          counted (600; 0: no limit); over it the job fails
``MISS_JOB_WRITE_MB``     model files one job may write, MB (4096; 0: no limit); over it
                          the job fails and what it wrote is removed
``MISS_QUOTA_MB``         disk one account's volumes and models may take, MB (20480; 0: no
                          quota); over it uploads and new jobs get 507
``MISS_TRUSTED_PROXIES``  addresses or networks (comma-separated) of the reverse proxies
                          whose ``X-Forwarded-For``/``-Proto`` are believed (none: the
                          headers are ignored, whoever sends them)
``MISS_PASSWORD_CHECKS``  passwords one server process checks at once (2); more logins
                          wait a few seconds for a turn, then get 429
``MISS_VOXEL_BUDGET_MB``  most voxel bytes a volume's full level sends the viewer (128)
``MISS_FORMAT_CACHE_MB``  disk the formats made on a model's first download (STL, PLY,
                          OBJ, VRML, X3D, 3MF) may take over all models, MB (2048; 0: no
                          cap); over it the least recently downloaded are removed, to be
                          made again when asked (``miss.server.storage.formats``)
"""

from __future__ import annotations

import ipaddress
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from miss.io.confined import Limits
from miss.pacs.server import PacsServer, configured_servers

MB = 1024 * 1024


@dataclass(frozen=True)
class Settings:
    """Where MISS keeps its data and how much it accepts; sizes in MB."""

    data_dir: Path = Path("miss-data")
    database_url: str = ""
    max_upload_mb: float = 2048.0
    max_unzipped_mb: float = 0.0
    workers: int = 1
    #: Worker processes kept started and warmed up ahead of jobs (0: each job starts its
    #: own, about a second later); each holds ~300 MB while it waits.
    spare_workers: int = 1
    demo: bool = True
    host: str = "127.0.0.1"
    port: int = 8000
    admin_password: str = field(default="", repr=False)
    session_hours: float = 12.0
    max_jobs_per_user: int = 2
    api_rate: float = 20.0
    api_burst: float = 200.0
    min_free_mb: float = 256.0
    worker_memory_mb: float | None = None
    in_memory_max_mb: float = 1024.0
    parse_seconds: float = 600.0
    uploads_per_user: int = 2
    uploads_at_once: int = 4
    #: The PACS MISS may search, import from and send to (``MISS_PACS_URL`` ...).
    pacs: tuple[PacsServer, ...] = ()
    pacs_imports: int = 2
    pacs_imports_per_user: int = 10
    pacs_send_uploads: bool = False
    lod_triangles: int = 2_000_000
    room_max_people: int = 50
    #: Jobs of one account run at once (0: ``workers`` less one, at least 1).
    workers_per_account: int = 0
    job_cpu_seconds: float = 600.0
    job_write_mb: float = 4096.0
    quota_mb: float = 20480.0
    #: Reverse proxies (addresses or networks) whose forwarded-for headers are believed.
    trusted_proxies: tuple[str, ...] = ()
    password_checks: int = 2
    upload_min_kbps: float = 8.0
    upload_rate_seconds: float = 30.0
    upload_idle_seconds: float = 60.0
    #: None: 5, or one less than ``room_max_people`` when that is 5 or fewer.
    room_reserved: int | None = None
    room_guests_per_link: int = 20
    sse_per_user: int = 10
    ws_connects_per_minute: float = 60.0
    parse_memory_mb: float = 4096.0
    voxel_budget_mb: float = 128.0
    #: Disk the formats made on request may take, MB (0: no cap).
    format_cache_mb: float = 2048.0

    def __post_init__(self) -> None:  # noqa: C901, PLR0915 (to split: issue 40)
        # Resolve once so the worker subprocesses, which get these as arguments, see the
        # same folder whatever their working directory.
        object.__setattr__(self, "data_dir", Path(self.data_dir).expanduser().resolve())
        if not self.database_url:
            object.__setattr__(self, "database_url", f"sqlite:///{self.data_dir / 'miss.sqlite3'}")
        if self.max_unzipped_mb <= 0:
            object.__setattr__(self, "max_unzipped_mb", 4.0 * self.max_upload_mb)
        if self.workers < 1:
            raise ValueError(f"MISS_WORKERS must be at least 1, got {self.workers}.")
        if self.workers_per_account < 0:
            raise ValueError(
                f"MISS_WORKERS_PER_ACCOUNT must be 0 (MISS_WORKERS less one) or more, "
                f"got {self.workers_per_account}."
            )
        if self.workers_per_account == 0:
            object.__setattr__(self, "workers_per_account", max(1, self.workers - 1))
        if self.spare_workers < 0:
            raise ValueError(f"MISS_SPARE_WORKERS must be 0 or more, got {self.spare_workers}.")
        if self.session_hours <= 0:
            raise ValueError(f"MISS_SESSION_HOURS must be positive, got {self.session_hours}.")
        if self.max_jobs_per_user < 1:
            raise ValueError(
                f"MISS_MAX_JOBS_PER_USER must be at least 1, got {self.max_jobs_per_user}."
            )
        if self.api_rate <= 0 or self.api_burst < 1:
            raise ValueError(
                f"MISS_API_RATE must be positive and MISS_API_BURST at least 1, "
                f"got {self.api_rate} and {self.api_burst}."
            )
        if self.in_memory_max_mb < 0:
            raise ValueError(
                f"MISS_IN_MEMORY_MAX_MB must be 0 or more, got {self.in_memory_max_mb}."
            )
        if self.min_free_mb < 0:
            raise ValueError(f"MISS_MIN_FREE_MB must be 0 or more, got {self.min_free_mb}.")
        if self.parse_seconds <= 0:
            raise ValueError(f"MISS_PARSE_SECONDS must be positive, got {self.parse_seconds}.")
        if self.uploads_per_user < 1 or self.uploads_at_once < self.uploads_per_user:
            raise ValueError(
                "MISS_UPLOADS_PER_USER must be at least 1 and MISS_UPLOADS_AT_ONCE at least "
                f"as large, got {self.uploads_per_user} and {self.uploads_at_once}."
            )
        if self.pacs_imports < 1:
            raise ValueError(f"MISS_PACS_IMPORTS must be at least 1, got {self.pacs_imports}.")
        if self.pacs_imports_per_user < 1:
            raise ValueError(
                f"MISS_PACS_IMPORTS_PER_USER must be at least 1, got {self.pacs_imports_per_user}."
            )
        if self.room_max_people < 1:
            raise ValueError(
                f"MISS_ROOM_MAX_PEOPLE must be at least 1, got {self.room_max_people}."
            )
        self._check_connections()
        if self.lod_triangles < 0:
            raise ValueError(f"MISS_LOD_TRIANGLES must be 0 or more, got {self.lod_triangles}.")
        for key, value in (
            ("MISS_JOB_CPU_SECONDS", self.job_cpu_seconds),
            ("MISS_JOB_WRITE_MB", self.job_write_mb),
            ("MISS_QUOTA_MB", self.quota_mb),
            ("MISS_FORMAT_CACHE_MB", self.format_cache_mb),
        ):
            if not value >= 0:
                raise ValueError(f"{key} must be 0 (no limit) or more, got {value}.")
        if self.worker_memory_mb is not None and not self.worker_memory_mb >= 0:
            raise ValueError(
                f"MISS_WORKER_MEMORY_MB must be a size in MB (0 for no cap), "
                f"got {self.worker_memory_mb}."
            )
        if not self.parse_memory_mb >= 0:
            raise ValueError(
                f"MISS_PARSE_MEMORY_MB must be a size in MB (0 for no cap), "
                f"got {self.parse_memory_mb}."
            )
        if self.password_checks < 1:
            raise ValueError(
                f"MISS_PASSWORD_CHECKS must be at least 1, got {self.password_checks}."
            )
        for proxy in self.trusted_proxies:
            try:
                _network(proxy)
            except ValueError as exc:
                raise ValueError(f"MISS_TRUSTED_PROXIES: {exc}") from None

    def _check_connections(self) -> None:
        """The settings that share connections and slots fairly among clients."""
        if not (self.upload_min_kbps >= 0 and self.upload_rate_seconds > 0):
            raise ValueError(
                "MISS_UPLOAD_MIN_KBPS must be 0 or more (0: no minimum) and "
                "MISS_UPLOAD_RATE_SECONDS positive, "
                f"got {self.upload_min_kbps} and {self.upload_rate_seconds}."
            )
        if not self.upload_idle_seconds > 0:
            raise ValueError(
                f"MISS_UPLOAD_IDLE_SECONDS must be positive, got {self.upload_idle_seconds}."
            )
        reserved = self.room_reserved
        if reserved is None:
            reserved = max(0, min(5, self.room_max_people - 1))
            object.__setattr__(self, "room_reserved", reserved)
        if not 0 <= reserved < self.room_max_people:
            raise ValueError(
                "MISS_ROOM_RESERVED must be 0 or more and less than MISS_ROOM_MAX_PEOPLE "
                f"({self.room_max_people}), got {self.room_reserved}."
            )
        if self.room_guests_per_link < 1:
            raise ValueError(
                f"MISS_ROOM_GUESTS_PER_LINK must be at least 1, got {self.room_guests_per_link}."
            )
        if self.sse_per_user < 1:
            raise ValueError(f"MISS_SSE_PER_USER must be at least 1, got {self.sse_per_user}.")
        if not self.ws_connects_per_minute >= 1:
            raise ValueError(
                "MISS_WS_CONNECTS_PER_MINUTE must be at least 1, "
                f"got {self.ws_connects_per_minute}."
            )

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None, **overrides: Any) -> Settings:
        """Settings from ``env`` (default ``os.environ``); keyword overrides win when not None."""
        env = os.environ if env is None else env
        values: dict[str, Any] = {}
        for name, key, cast in _ENV:
            if env.get(key, "").strip():
                values[name] = _parse(key, env[key].strip(), cast)
        values["pacs"] = configured_servers(env)
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**values)

    def pacs_server(self, name: str | None = None) -> PacsServer | None:
        """The PACS called ``name`` (the first when None); None when there is no such one."""
        if not name:
            return self.pacs[0] if self.pacs else None
        return next((p for p in self.pacs if p.name == name), None)

    @property
    def max_upload_bytes(self) -> int:
        """The upload cap (``MISS_MAX_UPLOAD_MB``) in bytes."""
        return int(self.max_upload_mb * MB)

    @property
    def max_unzipped_bytes(self) -> int:
        """The cap on an archive's unpacked size (``MISS_MAX_UNZIPPED_MB``) in bytes."""
        return int(self.max_unzipped_mb * MB)

    @property
    def in_memory_max_bytes(self) -> int:
        """The largest upload read in memory (``MISS_IN_MEMORY_MAX_MB``) in bytes."""
        return int(self.in_memory_max_mb * MB)

    @property
    def min_free_bytes(self) -> int:
        """Free disk space kept (``MISS_MIN_FREE_MB``) in bytes."""
        return int(self.min_free_mb * MB)

    def parse_limits(self) -> Limits:
        """Caps for the confined child that reads one upload."""
        return Limits(
            seconds=self.parse_seconds,
            memory_bytes=int(self.parse_memory_mb * MB),
            write_bytes=self.max_unzipped_bytes + (16 << 30),
            unzipped_bytes=self.max_unzipped_bytes,
            min_free_bytes=self.min_free_bytes,
        )

    @property
    def job_write_bytes(self) -> int:
        """What one job may write (``MISS_JOB_WRITE_MB``) in bytes."""
        return int(self.job_write_mb * MB)

    @property
    def quota_bytes(self) -> int:
        """One account's disk quota (``MISS_QUOTA_MB``) in bytes; 0: none."""
        return int(self.quota_mb * MB)

    @property
    def voxel_budget_bytes(self) -> int:
        """The voxel budget (``MISS_VOXEL_BUDGET_MB``) in bytes."""
        return int(self.voxel_budget_mb * MB)

    @property
    def format_cache_bytes(self) -> int:
        """The disk the formats made on request may take (``MISS_FORMAT_CACHE_MB``) in bytes;
        0: no cap."""
        return int(self.format_cache_mb * MB)

    def job_env(self) -> dict[str, str]:
        """The job limits as the worker reads them from its environment, so that settings
        given to ``create_app`` reach it as well as those of the server's environment."""
        return {
            "MISS_JOB_CPU_SECONDS": repr(self.job_cpu_seconds),
            "MISS_JOB_WRITE_MB": repr(self.job_write_mb),
        }

    @property
    def worker_memory_bytes(self) -> int:
        """What a job may allocate: the setting, or the machine's physical memory; 0: no cap."""
        if self.worker_memory_mb is None:
            return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        return int(self.worker_memory_mb * MB)


def _bool(text: str) -> bool:
    if text.lower() in ("1", "true", "yes", "on"):
        return True
    if text.lower() in ("0", "false", "no", "off"):
        return False
    raise ValueError("expected 1/0, true/false, yes/no or on/off")


_ENV: tuple[tuple[str, str, Any], ...] = (
    ("data_dir", "MISS_DATA_DIR", Path),
    ("database_url", "MISS_DATABASE_URL", str),
    ("max_upload_mb", "MISS_MAX_UPLOAD_MB", float),
    ("max_unzipped_mb", "MISS_MAX_UNZIPPED_MB", float),
    ("workers", "MISS_WORKERS", int),
    ("spare_workers", "MISS_SPARE_WORKERS", int),
    ("demo", "MISS_DEMO", _bool),
    ("host", "MISS_HOST", str),
    ("port", "MISS_PORT", int),
    ("admin_password", "MISS_ADMIN_PASSWORD", str),
    ("session_hours", "MISS_SESSION_HOURS", float),
    ("max_jobs_per_user", "MISS_MAX_JOBS_PER_USER", int),
    ("api_rate", "MISS_API_RATE", float),
    ("api_burst", "MISS_API_BURST", float),
    ("min_free_mb", "MISS_MIN_FREE_MB", float),
    ("worker_memory_mb", "MISS_WORKER_MEMORY_MB", float),
    ("in_memory_max_mb", "MISS_IN_MEMORY_MAX_MB", float),
    ("parse_seconds", "MISS_PARSE_SECONDS", float),
    ("uploads_per_user", "MISS_UPLOADS_PER_USER", int),
    ("uploads_at_once", "MISS_UPLOADS_AT_ONCE", int),
    ("pacs_imports", "MISS_PACS_IMPORTS", int),
    ("pacs_imports_per_user", "MISS_PACS_IMPORTS_PER_USER", int),
    ("pacs_send_uploads", "MISS_PACS_SEND_UPLOADS", _bool),
    ("lod_triangles", "MISS_LOD_TRIANGLES", int),
    ("room_max_people", "MISS_ROOM_MAX_PEOPLE", int),
    ("workers_per_account", "MISS_WORKERS_PER_ACCOUNT", int),
    ("job_cpu_seconds", "MISS_JOB_CPU_SECONDS", float),
    ("job_write_mb", "MISS_JOB_WRITE_MB", float),
    ("quota_mb", "MISS_QUOTA_MB", float),
    ("trusted_proxies", "MISS_TRUSTED_PROXIES", lambda text: _networks(text)),
    ("password_checks", "MISS_PASSWORD_CHECKS", int),
    ("upload_min_kbps", "MISS_UPLOAD_MIN_KBPS", float),
    ("upload_rate_seconds", "MISS_UPLOAD_RATE_SECONDS", float),
    ("upload_idle_seconds", "MISS_UPLOAD_IDLE_SECONDS", float),
    ("room_reserved", "MISS_ROOM_RESERVED", int),
    ("room_guests_per_link", "MISS_ROOM_GUESTS_PER_LINK", int),
    ("sse_per_user", "MISS_SSE_PER_USER", int),
    ("ws_connects_per_minute", "MISS_WS_CONNECTS_PER_MINUTE", float),
    ("parse_memory_mb", "MISS_PARSE_MEMORY_MB", float),
    ("voxel_budget_mb", "MISS_VOXEL_BUDGET_MB", float),
    ("format_cache_mb", "MISS_FORMAT_CACHE_MB", float),
)


def _networks(text: str) -> tuple[str, ...]:
    """``MISS_TRUSTED_PROXIES``: comma-separated addresses or networks, each checked."""
    return tuple(_network(item.strip()) for item in text.split(",") if item.strip())


def _network(text: str) -> str:
    try:
        ipaddress.ip_network(text, strict=False)
    except ValueError:
        raise ValueError(
            f"{text!r} is not an IP address or network; give the addresses of your "
            "reverse proxies, e.g. 127.0.0.1 or 10.0.0.0/24."
        ) from None
    return text


def _parse(key: str, text: str, cast: Any) -> Any:
    try:
        return cast(text)
    except ValueError as exc:
        raise ValueError(f"{key}={text!r} is not valid: {exc}") from None
