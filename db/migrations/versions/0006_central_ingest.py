"""The central site (issue 17): where a node reports from (its site and gateway), gateway keys
scoped to one site, where an alert event came from (``origin`` edge for an ingested one), and the
uids of every record ingested from the edges (each stored once: a replayed batch duplicates nothing).

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-01
"""
from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

UTC = sa.DateTime(timezone=True)
ROLES_BEFORE = ("viewer", "operator", "admin")
ROLES = (*ROLES_BEFORE, "gateway")


def _roles_check(roles: Sequence[str]) -> str:
    return "role IN ({})".format(", ".join(f"'{r}'" for r in roles))


def upgrade() -> None:
    op.add_column("nodes", sa.Column("site", sa.String(64), nullable=True))
    op.add_column("nodes", sa.Column("gateway_id", sa.String(64), nullable=True))
    op.create_index(op.f("ix_nodes_site_gateway_id"), "nodes", ["site", "gateway_id"])
    op.add_column("events", sa.Column("origin", sa.String(16), nullable=True))
    with op.batch_alter_table("api_keys") as batch:  # SQLite changes a CHECK by copying the table
        batch.drop_constraint(op.f("ck_api_keys_role"), type_="check")
        batch.create_check_constraint(op.f("ck_api_keys_role"), _roles_check(ROLES))
        batch.add_column(sa.Column("site", sa.String(64), nullable=True))
    op.create_table(
        "ingested_records",
        sa.Column("uid", sa.String(200), nullable=False),
        sa.Column("gateway_id", sa.String(64), nullable=False),
        sa.Column("kind", sa.String(32), nullable=False),
        sa.Column("central_id", sa.String(64), nullable=False),
        sa.Column("batch_id", sa.Uuid(), nullable=False),
        sa.Column("stored_at", UTC, nullable=False),
        sa.PrimaryKeyConstraint("uid", name=op.f("pk_ingested_records")),
    )


def downgrade() -> None:
    op.drop_table("ingested_records")
    with op.batch_alter_table("api_keys") as batch:
        batch.drop_column("site")
        batch.drop_constraint(op.f("ck_api_keys_role"), type_="check")
        batch.create_check_constraint(op.f("ck_api_keys_role"), _roles_check(ROLES_BEFORE))
    with op.batch_alter_table("events") as batch:
        batch.drop_column("origin")
    op.drop_index(op.f("ix_nodes_site_gateway_id"), table_name="nodes")
    with op.batch_alter_table("nodes") as batch:
        batch.drop_column("gateway_id")
        batch.drop_column("site")
