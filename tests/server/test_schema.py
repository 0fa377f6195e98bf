"""The schema is kept by Alembic on both engines: a new database is made by the
migrations and equals the tables MISS declares; a data folder from before Alembic is
stamped and upgraded without losing a row."""

from __future__ import annotations

from pathlib import Path

from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import create_engine, select, text
from support.pg import sqlalchemy_url, sqlite_only

from miss.server.storage import schema
from miss.server.storage.db import Base, ShareRow, UserRow, VolumeRow, utcnow
from miss.server.storage.store import Store


def test_new_database_is_made_by_the_migrations_and_equals_the_tables(tmp_path: Path) -> None:
    store = Store(tmp_path, sqlalchemy_url(tmp_path))
    store.init()
    try:
        with store.engine.connect() as conn:
            assert schema.current(conn) == schema.head()
            diff = compare_metadata(MigrationContext.configure(conn), Base.metadata)
        assert diff == []
        schema.upgrade(store.engine)  # again: nothing to do
    finally:
        store.close()


@sqlite_only("data folders from before Alembic were SQLite files")
def test_folder_from_before_alembic_keeps_its_rows(tmp_path: Path) -> None:
    """A database as MISS made it before (``create_all``, then ALTERs for later columns):
    two of those columns missing, a user, a volume and a share link in it."""
    url = sqlalchemy_url(tmp_path)
    tmp_path.mkdir(exist_ok=True)
    engine = create_engine(url)
    Base.metadata.create_all(engine)
    with engine.begin() as conn:
        conn.execute(text("ALTER TABLE models DROP COLUMN runner"))  # came with Alembic
        conn.execute(text("ALTER TABLE users DROP COLUMN pacs"))
        conn.execute(text("ALTER TABLE shares DROP COLUMN message"))
        now = utcnow()
        conn.execute(
            text(
                "INSERT INTO users (id, name, password, is_admin, created_at, disabled) "
                "VALUES ('u1', 'ann', 'x', 0, :now, 0)"
            ),
            {"now": now},
        )
        conn.execute(
            text(
                "INSERT INTO volumes (id, owner_id, name, slug, created_at, info) "
                """VALUES ('v1', 'u1', 'Head', 'head', :now, '{"dims": [2, 2, 2]}')"""
            ),
            {"now": now},
        )
        conn.execute(
            text(
                "INSERT INTO shares (id, token_hash, owner_id, volume_id, label, "
                "can_download, can_annotate, created_at, expires_at) "
                "VALUES ('s1', :hash, 'u1', 'v1', '', 1, 0, :now, :now)"
            ),
            {"now": now, "hash": "h" * 64},
        )
    engine.dispose()

    store = Store(tmp_path, url)
    store.init()
    try:
        with store.session() as s:
            user = s.scalars(select(UserRow)).one()
            share = s.scalars(select(ShareRow)).one()
            volume = s.scalars(select(VolumeRow)).one()
        assert (user.name, user.pacs, user.disabled) == ("ann", False, False)
        assert (share.message, share.can_download, share.volume_id) == ("", True, "v1")
        assert volume.info == {"dims": [2, 2, 2]}
        with store.engine.connect() as conn:
            assert schema.current(conn) == schema.head()
    finally:
        store.close()
