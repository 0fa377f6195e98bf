"""shares.can_view_volume: a link may offer the scan itself (its de-identified voxels) in
the guest's 3-D view; links made before it show the surfaces only.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-28
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # A database from before Alembic whose shares table was only now made (by
    # ``schema.upgrade``, from today's tables) has the column already.
    columns = {c["name"] for c in sa.inspect(op.get_bind()).get_columns("shares")}
    if "can_view_volume" in columns:
        return
    with op.batch_alter_table("shares", schema=None) as batch_op:
        batch_op.add_column(
            sa.Column("can_view_volume", sa.Boolean(), nullable=False, server_default=sa.false())
        )


def downgrade() -> None:
    with op.batch_alter_table("shares", schema=None) as batch_op:
        batch_op.drop_column("can_view_volume")
