"""A throw-away PostgreSQL cluster for the tests: Debian's ``postgresql`` binaries, a
temporary folder, a free loopback port, fsync off; never the system's service or 5432.

``MISS_TEST_DATABASE=postgres`` runs the server tests on it (``database_url``); without
it they use SQLite files in their data folders, as a default installation does.

PostgreSQL refuses to run as root, so as root (the CI machine) the cluster runs as the
``postgres`` user that Debian's package creates, in a folder that user owns.
"""

from __future__ import annotations

import atexit
import hashlib
import os
import pwd
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import pytest

from miss.server.core.settings import Settings
from support import free_port


def _bin() -> Path:
    """Debian's newest installed PostgreSQL (``MISS_PG_BIN`` to choose another)."""
    if os.environ.get("MISS_PG_BIN"):
        return Path(os.environ["MISS_PG_BIN"])
    found = sorted(Path("/usr/lib/postgresql").glob("*/bin"), key=lambda p: int(p.parent.name))
    return found[-1] if found else Path("/usr/lib/postgresql/15/bin")


BIN = _bin()
#: Which engine the server tests use: "sqlite" (default) or "postgres".
ENGINE = os.environ.get("MISS_TEST_DATABASE", "sqlite").strip().lower() or "sqlite"


def sqlite_only(why: str) -> pytest.MarkDecorator:
    """Skip a test about SQLite itself when the run is on PostgreSQL."""
    return pytest.mark.skipif(ENGINE != "sqlite", reason=f"SQLite only: {why}")


def missing() -> str | None:
    """Why no cluster can start here (None when it can)."""
    try:
        import psycopg  # noqa: F401
    except ImportError:
        return "psycopg not installed (pip install -e '.[test]')"
    for tool in ("initdb", "postgres"):
        if not (BIN / tool).is_file():
            return f"PostgreSQL not installed ({BIN / tool} missing; `make postgres` installs it)"
    if os.geteuid() == 0:
        try:
            pwd.getpwnam("postgres")
        except KeyError:
            return "running as root without a 'postgres' user to run PostgreSQL as"
    return None


class Cluster:
    """One ``postgres`` server in a temporary folder; ``url(db)`` for SQLAlchemy."""

    def __init__(self) -> None:
        reason = missing()
        if reason:
            raise RuntimeError(reason)
        self.folder = Path(tempfile.mkdtemp(prefix="miss-pg-"))
        self.as_user: list[str] = []
        if os.geteuid() == 0:
            user = pwd.getpwnam("postgres")
            os.chown(self.folder, user.pw_uid, user.pw_gid)
            self.as_user = ["runuser", "-u", "postgres", "--"]
        self.data = self.folder / "data"
        self.port = free_port()
        self.user = "postgres" if self.as_user else pwd.getpwuid(os.geteuid()).pw_name
        self._run(
            BIN / "initdb",
            "-D",
            self.data,
            "-U",
            self.user,
            "--auth=trust",
            "--encoding=UTF8",
            "--no-sync",
        )
        self.log = self.folder / "postgres.log"
        options = {
            "listen_addresses": "127.0.0.1",
            "port": self.port,
            "unix_socket_directories": self.folder,
            "fsync": "off",
            "synchronous_commit": "off",
            "full_page_writes": "off",
            "max_connections": 1000,
            "shared_buffers": "64MB",
        }
        args = [a for k, v in options.items() for a in ("-c", f"{k}={v}")]
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen(
                [*self.as_user, BIN / "postgres", "-D", self.data, *args],
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
            )
        try:
            self._wait_ready()
        except BaseException:
            self.stop()
            raise

    def _run(self, *cmd: object) -> None:
        subprocess.run(
            [*self.as_user, *map(str, cmd)], check=True, capture_output=True, timeout=120
        )

    def _wait_ready(self, timeout: float = 60) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"postgres exited:\n{self.log.read_text()}")
            try:
                with self.connect():
                    return
            except Exception:  # psycopg.OperationalError: not accepting connections yet
                time.sleep(0.1)
        raise RuntimeError(f"postgres not ready after {timeout} s:\n{self.log.read_text()}")

    def url(self, database: str = "postgres") -> str:
        return f"postgresql+psycopg://{self.user}@127.0.0.1:{self.port}/{database}"

    def connect(self, database: str = "postgres") -> Any:
        import psycopg

        return psycopg.connect(
            host="127.0.0.1", port=self.port, user=self.user, dbname=database, autocommit=True
        )

    def create(self, name: str, template: str | None = None) -> str:
        """A new database ``name`` (a copy of ``template`` when given); its URL."""
        from psycopg import sql

        query = sql.SQL("CREATE DATABASE {}").format(sql.Identifier(name))
        if template:
            query += sql.SQL(" TEMPLATE {}").format(sql.Identifier(template))
        with self.connect() as conn:
            conn.execute(query)
        return self.url(name)

    def exists(self, name: str) -> bool:
        with self.connect() as conn:
            found = conn.execute("SELECT 1 FROM pg_database WHERE datname = %s", (name,))
            return found.fetchone() is not None

    def stop(self) -> None:
        """Fast shutdown (clients still connected are disconnected), folder removed."""
        if self.proc.poll() is None:
            stop = [*self.as_user, str(BIN / "pg_ctl"), "-D", str(self.data), "-m", "fast"]
            subprocess.run([*stop, "-w", "stop"], capture_output=True, timeout=60)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        shutil.rmtree(self.folder, ignore_errors=True)


_shared: Cluster | None = None


def shared() -> Cluster:
    """This test process's one cluster, started on first use and stopped at exit."""
    global _shared
    if _shared is None:
        _shared = Cluster()
        atexit.register(_shared.stop)
    return _shared


def database_name(data_dir: Path) -> str:
    """The database that goes with a test's data folder (a name PostgreSQL accepts)."""
    digest = hashlib.sha1(str(Path(data_dir).resolve()).encode()).hexdigest()[:20]
    return f"miss_{digest}"


def database_url(data_dir: Path, template: Path | None = None) -> str:
    """The database URL a server on ``data_dir`` should use in this test run: "" (the
    SQLite file in the folder) unless ``MISS_TEST_DATABASE=postgres``; then a database of
    its own, made on first ask, as a copy of ``template``'s when given (``copy_seed``)."""
    if ENGINE != "postgres":
        return ""
    if reason := missing():
        pytest.skip(reason)
    cluster = shared()
    name = database_name(data_dir)
    if not cluster.exists(name):
        cluster.create(name, database_name(template) if template else None)
    return cluster.url(name)


def sqlalchemy_url(data_dir: Path) -> str:
    """The URL a test opens ``data_dir``'s database with, whichever the engine."""
    return database_url(data_dir) or Settings(data_dir=data_dir).database_url


def settings_for(data_dir: Path, **values: Any) -> Settings:
    """Settings of a test server on ``data_dir`` with this run's database."""
    values.setdefault("database_url", database_url(data_dir))
    # No spare worker unless a test asks (tests/server/test_progressive.py does): a spare
    # imports and warms up everything a job uses (about 3 s of a core), wasted in an app
    # that runs no job or is closed before its next one; each job starts its own worker.
    values.setdefault("spare_workers", 0)
    return Settings(data_dir=data_dir, **values)


def copy_seed(seeded_dir: Path, dest: Path) -> Path:
    """A copy of the seeded folder, and of its database when that is not in the folder."""
    shutil.copytree(seeded_dir, dest)
    database_url(dest, template=seeded_dir)
    return dest
