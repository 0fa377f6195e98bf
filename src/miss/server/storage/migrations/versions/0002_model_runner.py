"""models.runner: the server process running a job, so that another one can queue it
again when that process is gone (several processes on one PostgreSQL database).

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-26
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # A database from before Alembic whose models table was only now made (by
    # ``schema._stamp_legacy``, from today's tables) has the column already.
    columns = {c["name"] for c in sa.inspect(op.get_bind()).get_columns("models")}
    if "runner" in columns:
        return
    with op.batch_alter_table("models", schema=None) as batch_op:
        batch_op.add_column(sa.Column("runner", sa.String(length=32), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("models", schema=None) as batch_op:
        batch_op.drop_column("runner")
