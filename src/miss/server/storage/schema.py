"""The database's schema, kept by Alembic on both engines (``migrations/``).

``upgrade(engine)`` brings any database to the newest revision: a new one gets every
table, one made by an earlier MISS (tables made by ``create_all`` and the ALTERs of
``db.ADDED_COLUMNS``, no ``alembic_version`` table) gets those columns it still lacks and
and the tables it lacks, is stamped with the first revision, which is that schema, then
upgraded like any other (a revision adding a column checks whether a table made just now
has it already).

Servers that start at once on one PostgreSQL database take turns (an advisory lock held
for the transaction), so only one of them migrates. A new table or column is one more
revision: ``alembic -c src/miss/server/storage/migrations/alembic.ini -x url=sqlite:///x
revision --autogenerate -m "what"`` against a database at the previous head.
"""

from __future__ import annotations

from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Connection, Engine, inspect, text

from miss.server.storage.db import ADDED_COLUMNS, Base

MIGRATIONS = Path(__file__).with_name("migrations")
#: The revision equal to the schema of MISS before Alembic (``create_all`` + ALTERs).
BASELINE = "0001"
#: Key of the PostgreSQL advisory lock held while migrating ("MISS" in ASCII).
LOCK_KEY = 0x4D495353


def config(connection: Connection | None = None) -> Config:
    """Alembic's configuration for MISS's migrations, on ``connection`` if given."""
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    cfg.attributes["connection"] = connection
    return cfg


def head() -> str:
    """The newest revision this MISS knows."""
    head = ScriptDirectory.from_config(config()).get_current_head()
    assert head is not None
    return head


def current(connection: Connection) -> str | None:
    """The revision the database is at (None: new, or from before Alembic)."""
    return MigrationContext.configure(connection).get_current_revision()


def upgrade(engine: Engine) -> None:
    """Bring the database to ``head()`` (see the module's docstring); at head, only reads."""
    with engine.begin() as conn:
        if conn.dialect.name == "postgresql":
            conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": LOCK_KEY})
        elif current(conn) == head():
            return  # SQLite: beside a running server (``miss user``), take no write lock
        tables = set(inspect(conn).get_table_names())
        if tables and "alembic_version" not in tables:
            _add_legacy_columns(conn, tables)
            # Tables an old version did not have yet, as ``create_all`` made them then.
            Base.metadata.create_all(conn)
            command.stamp(config(conn), BASELINE)
        command.upgrade(config(conn), "head")


def _add_legacy_columns(conn: Connection, tables: set[str]) -> None:
    """The ALTERs that made an old database equal to the baseline revision."""
    inspector = inspect(conn)
    for table, column, sql_type in ADDED_COLUMNS:
        if table in tables and column not in {c["name"] for c in inspector.get_columns(table)}:
            conn.execute(text(f"ALTER TABLE {table} ADD COLUMN {column} {sql_type}"))
