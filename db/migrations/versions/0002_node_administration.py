"""Node administration: an operator-facing label, location and notes, and decommissioning
(who, when, why), all kept on the node.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-30
"""
from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# Frozen copies of the types at this revision.
UTC = sa.DateTime(timezone=True)
COLUMNS = (
    ("label", sa.String(128)),
    ("location", sa.String(256)),
    ("notes", sa.Text()),
    ("details_updated_at", UTC),
    ("details_updated_by", sa.String(128)),
    ("decommissioned_at", UTC),
    ("decommissioned_by", sa.String(128)),
    ("decommission_reason", sa.Text()),
)


def upgrade() -> None:
    # Nullable columns only: a plain ADD COLUMN on both backends, existing nodes keep their rows.
    for name, type_ in COLUMNS:
        op.add_column("nodes", sa.Column(name, type_, nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("nodes") as batch:  # SQLite drops columns by copying the table
        for name, _ in reversed(COLUMNS):
            batch.drop_column(name)
