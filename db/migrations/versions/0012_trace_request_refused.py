"""A trace request whose re-sent measurement the centre refused ends ``refused``, with why (issue 17,
a request answered ``held`` waited forever when the record with its traces was then refused).

* ``trace_requests.status`` takes ``refused``: its CHECK constraint is made again with the new list
  (SQLite: the table is copied, batch mode; nothing refers to ``trace_requests``, so its copy
  keeps every foreign key; PostgreSQL: the constraint is dropped and added).
* ``trace_requests.refused_at`` and ``trace_requests.refusal`` (nullable): when the centre last
  refused the gateway's re-sent record, and the refusal it answered.

Downgrading forgets the ``refused`` requests (the revision before cannot hold them): their
measurements show ``at_gateway`` again and can be asked for again.

Revision ID: 0012
Revises: 0011
Create Date: 2027-01-24
"""
from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0012"
down_revision: str | None = "0011"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# Frozen copies of the types and values at this revision.
UTC = sa.DateTime(timezone=True)
CHECK = "ck_trace_requests_trace_request_status"  # revision 0009's name (the naming convention applied)
STATUSES_0009 = ("requested", "held", "received", "pruned")
STATUSES = (*STATUSES_0009, "refused")


def _status_in(statuses: Sequence[str]) -> str:
    return "status IN ({})".format(", ".join(f"'{value}'" for value in statuses))


def upgrade() -> None:
    with op.batch_alter_table("trace_requests", recreate="auto") as batch:
        batch.drop_constraint(op.f(CHECK), type_="check")
        batch.create_check_constraint(op.f(CHECK), _status_in(STATUSES))
        batch.add_column(sa.Column("refused_at", UTC, nullable=True))
        batch.add_column(sa.Column("refusal", sa.Text(), nullable=True))


def downgrade() -> None:
    op.execute("DELETE FROM trace_requests WHERE status = 'refused'")
    with op.batch_alter_table("trace_requests", recreate="auto") as batch:
        batch.drop_column("refusal")
        batch.drop_column("refused_at")
        batch.drop_constraint(op.f(CHECK), type_="check")
        batch.create_check_constraint(op.f(CHECK), _status_in(STATUSES_0009))
