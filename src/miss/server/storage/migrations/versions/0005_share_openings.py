"""share_openings: which signed-in users opened which share links, and when last (the
library's "Shared with me").

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-28
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # A database from before Alembic had its missing tables made from today's (by
    # ``schema.upgrade``), this one included.
    if "share_openings" in sa.inspect(op.get_bind()).get_table_names():
        return
    op.create_table(
        "share_openings",
        sa.Column("share_id", sa.String(length=32), nullable=False),
        sa.Column("user_id", sa.String(length=32), nullable=False),
        sa.Column("opened_at", sa.DateTime(), nullable=False),
        sa.ForeignKeyConstraint(["share_id"], ["shares.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["user_id"], ["users.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("share_id", "user_id"),
    )
    with op.batch_alter_table("share_openings", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_share_openings_user_id"), ["user_id"], unique=False)


def downgrade() -> None:
    with op.batch_alter_table("share_openings", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_share_openings_user_id"))
    op.drop_table("share_openings")
