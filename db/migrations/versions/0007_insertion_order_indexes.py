"""Lists and "latest" go by insertion (id), not by a timestamp a clock can forge (issue 15.1): an index
on (node_id, id) for each node's measurements, detections and state changes keeps every page one
index range scan.

Revision ID: 0007
Revises: 0006
Create Date: 2026-12-01
"""
from __future__ import annotations

from collections.abc import Sequence

from alembic import op

revision: str = "0007"
down_revision: str | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

INDEXES = (
    ("ix_measurements_node_id_order", "measurements"),
    ("ix_detections_node_id_order", "detections"),
    ("ix_state_changes_node_id_order", "state_changes"),
)


def upgrade() -> None:
    for name, table in INDEXES:
        op.create_index(name, table, ["node_id", "id"])


def downgrade() -> None:
    for name, table in reversed(INDEXES):
        op.drop_index(name, table_name=table)
