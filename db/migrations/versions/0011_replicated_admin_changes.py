"""What an operator changes through a gateway's API reaches the centre (issue 17, a replication gap).

* ``nodes.revision``: this database's count of changes to a node's replicated view (an INFO, an
  admin's details, decommissioning, recommissioning); a node record carries it, so at the centre
  a later change wins over an older record even when ``last_seen_at`` did not move.
* ``nodes.source_revision`` (central site): the revision of the gateway's node record last applied
  here (NULL: none yet, or one from a gateway that sends none).
* ``uplink_config``: one row while the gateway that owns this database replicates to a centre
  (its ``send`` policy), so every process writing the database (the gateway's API too) queues
  what it changes; no row: nothing queues.

Revision ID: 0011
Revises: 0010
Create Date: 2027-01-10
"""
from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0011"
down_revision: str | None = "0010"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

UTC = sa.DateTime(timezone=True)


def upgrade() -> None:
    op.add_column("nodes", sa.Column("revision", sa.Integer(), nullable=False, server_default="0"))
    op.add_column("nodes", sa.Column("source_revision", sa.Integer(), nullable=True))
    op.create_table(
        "uplink_config",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("send", sa.String(32), nullable=False),
        sa.Column("since", UTC, nullable=False),
        sa.CheckConstraint("id = 1", name=op.f("ck_uplink_config_one_row")),
        sa.CheckConstraint("send IN ('everything', 'flagged_traces')", name=op.f("ck_uplink_config_send")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_uplink_config")),
    )


def downgrade() -> None:
    op.drop_table("uplink_config")
    op.drop_column("nodes", "source_revision")  # SQLite 3.35+: no copy of the table
    op.drop_column("nodes", "revision")
