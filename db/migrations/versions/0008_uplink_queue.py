"""The uplink queue: records to replicate to a central PipeSentry, written with the facts they
replicate, marked when the centre acknowledged them (docs/storage.md, "Uplink queue").

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-01
"""
from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0008"
down_revision: str | None = "0007"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# Frozen copies of the types at this revision.
UTC = sa.DateTime(timezone=True)
BIG_ID = sa.BigInteger().with_variant(sa.Integer(), "sqlite")
KINDS = ("node", "measurement", "baseline", "detection", "state_change", "alert_event")
STATUSES = ("pending", "sent", "refused")


def _one_of(column: str, values: Sequence[str], name: str) -> sa.CheckConstraint:
    listed = ", ".join(f"'{value}'" for value in values)
    return sa.CheckConstraint(f"{column} IN ({listed})", name=op.f(name))


def upgrade() -> None:
    op.create_table(
        "uplink_queue",
        sa.Column("id", BIG_ID, nullable=False),
        sa.Column("kind", sa.String(32), nullable=False),
        sa.Column("node_id", sa.String(64), nullable=True),
        sa.Column("ref", sa.String(64), nullable=False),
        sa.Column("measurement_id", BIG_ID, nullable=True),
        sa.Column("with_traces", sa.Boolean(), nullable=False, server_default=sa.false()),
        sa.Column("created_at", UTC, nullable=False),
        sa.Column("status", sa.String(32), nullable=False),
        sa.Column("sent_at", UTC, nullable=True),
        sa.Column("refusals", sa.Integer(), nullable=False, server_default="0"),
        sa.Column("last_error", sa.Text(), nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_uplink_queue")),
        sa.ForeignKeyConstraint(["node_id"], ["nodes.node_id"], name=op.f("fk_uplink_queue_node_id_nodes")),
        sa.ForeignKeyConstraint(
            ["measurement_id"], ["measurements.id"], name=op.f("fk_uplink_queue_measurement_id_measurements")
        ),
        _one_of("kind", KINDS, "ck_uplink_queue_uplink_kind"),
        _one_of("status", STATUSES, "ck_uplink_queue_uplink_status"),
    )
    op.create_index("ix_uplink_queue_status_node", "uplink_queue", ["status", "node_id", "id"])
    op.create_index("ix_uplink_queue_node_kind", "uplink_queue", ["node_id", "kind", "id"])
    op.create_index("ix_uplink_queue_measurement", "uplink_queue", ["measurement_id"])


def downgrade() -> None:
    op.drop_index("ix_uplink_queue_measurement", table_name="uplink_queue")
    op.drop_index("ix_uplink_queue_node_kind", table_name="uplink_queue")
    op.drop_index("ix_uplink_queue_status_node", table_name="uplink_queue")
    op.drop_table("uplink_queue")
