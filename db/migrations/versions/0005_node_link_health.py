"""The link as the gateway last found it, on the node: who answers on the port (INFO's node_id),
its boot id, how many reboots the gateway noticed and when the last was, the settings it
applied and how either differs from the configuration; and the boot each measurement was
taken in.

Revision ID: 0005
Revises: 0004
Create Date: 2026-12-01
"""
from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# Frozen copies of the types at this revision.
UTC = sa.DateTime(timezone=True)
JSON = sa.JSON().with_variant(postgresql.JSONB(), "postgresql")
NODE_COLUMNS = (
    ("reported_node_id", sa.String(64)),
    ("boot_id", sa.BigInteger()),
    ("last_reboot_at", UTC),
    ("applied_settings", JSON),
    ("link_problems", JSON),
)


def upgrade() -> None:
    for name, type_ in NODE_COLUMNS:
        op.add_column("nodes", sa.Column(name, type_, nullable=True))
    op.add_column("nodes", sa.Column("reboots", sa.Integer(), nullable=False, server_default="0"))
    op.add_column("measurements", sa.Column("boot_id", sa.BigInteger(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("measurements") as batch:
        batch.drop_column("boot_id")
    with op.batch_alter_table("nodes") as batch:  # SQLite drops columns by copying the table
        batch.drop_column("reboots")
        for name, _ in reversed(NODE_COLUMNS):
            batch.drop_column(name)
