"""models.name: a display name its owner gives a model (the page's Rename).

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-28
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # A database from before Alembic whose models table was only now made (by
    # ``schema._stamp_legacy``, from today's tables) has the column already.
    columns = {c["name"] for c in sa.inspect(op.get_bind()).get_columns("models")}
    if "name" in columns:
        return
    with op.batch_alter_table("models", schema=None) as batch_op:
        batch_op.add_column(sa.Column("name", sa.String(length=200), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("models", schema=None) as batch_op:
        batch_op.drop_column("name")
