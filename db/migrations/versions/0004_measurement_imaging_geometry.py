"""Measurements keep the wave velocity and wall thickness the gateway imaged them with.

An exported record then reproduces the gateway's map exactly; rows stored before this
revision have neither (NULL: the T(0,1) default velocity, no wall).

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-01
"""
from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("measurements", sa.Column("velocity_m_s", sa.Float(), nullable=True))
    op.add_column("measurements", sa.Column("wall_mm", sa.Float(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("measurements") as batch:
        batch.drop_column("wall_mm")
        batch.drop_column("velocity_m_s")
