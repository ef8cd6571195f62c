"""Raw traces on demand (issue 17): a central operator's requests for the traces of measurements a
gateway sent without them, polled by the gateway (docs/storage.md, "Trace requests"); and an index
to find a measurement's edge uid from its central id.

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-02
"""
from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0009"
down_revision: str | None = "0008"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# Frozen copies of the types at this revision.
UTC = sa.DateTime(timezone=True)
BIG_ID = sa.BigInteger().with_variant(sa.Integer(), "sqlite")
STATUSES = ("requested", "held", "received", "pruned")


def upgrade() -> None:
    listed = ", ".join(f"'{value}'" for value in STATUSES)
    op.create_table(
        "trace_requests",
        sa.Column("id", BIG_ID, nullable=False),
        sa.Column("measurement_id", BIG_ID, nullable=False),
        sa.Column("measurement_uid", sa.String(200), nullable=False),
        sa.Column("gateway_id", sa.String(64), nullable=False),
        sa.Column("site", sa.String(64), nullable=False),
        sa.Column("status", sa.String(32), nullable=False),
        sa.Column("requested_by", sa.String(128), nullable=False),
        sa.Column("requested_at", UTC, nullable=False),
        sa.Column("answered_at", UTC, nullable=True),
        sa.Column("received_at", UTC, nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_trace_requests")),
        sa.ForeignKeyConstraint(
            ["measurement_id"], ["measurements.id"], name=op.f("fk_trace_requests_measurement_id_measurements")
        ),
        sa.UniqueConstraint("measurement_id", name=op.f("uq_trace_requests_measurement_id")),
        sa.CheckConstraint(f"status IN ({listed})", name=op.f("ck_trace_requests_trace_request_status")),
    )
    op.create_index("ix_trace_requests_pending", "trace_requests", ["site", "gateway_id", "status", "id"])
    op.create_index("ix_ingested_records_kind_central_id", "ingested_records", ["kind", "central_id"])


def downgrade() -> None:
    op.drop_index("ix_ingested_records_kind_central_id", table_name="ingested_records")
    op.drop_index("ix_trace_requests_pending", table_name="trace_requests")
    op.drop_table("trace_requests")
