"""Alembic's environment for MISS's database: ``Store.init_schema`` runs it with an open
connection (``config.attributes["connection"]``); ``alembic`` on the command line with
``-x url=...`` (see ``miss.server.storage.schema``)."""

from __future__ import annotations

from alembic import context
from sqlalchemy import Connection, create_engine

from miss.server.storage.db import Base

config = context.config


def run(connection: Connection) -> None:
    # Batch mode: SQLite alters a table by copying it, which Alembic does for us.
    context.configure(
        connection=connection,
        target_metadata=Base.metadata,
        render_as_batch=True,
        compare_type=True,
    )
    with context.begin_transaction():
        context.run_migrations()


connection = config.attributes.get("connection")
if connection is not None:
    run(connection)
else:
    url = context.get_x_argument(as_dictionary=True).get("url") or config.get_main_option(
        "sqlalchemy.url"
    )
    if not url:
        raise RuntimeError("no database URL: pass -x url=... or set sqlalchemy.url")
    engine = create_engine(url)
    with engine.connect() as conn:
        run(conn)
    engine.dispose()
