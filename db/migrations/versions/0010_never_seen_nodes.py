"""A configured node that never answered has a row (issue 15): the gateway registers every node
of its configuration when it starts, before any INFO reply, so what INFO tells (firmware,
protocol version, channels, sample rate, geometry) and when the node was first and last seen
may be unknown (NULL); ``watched_since`` is when this database started watching the node (its
first INFO for a node registered that way before this revision).

Downgrading forgets the nodes never seen, with their events, deliveries and queued records:
the revision before cannot hold a node without its INFO.

Revision ID: 0010
Revises: 0009
Create Date: 2026-12-01
"""
from __future__ import annotations

import re
from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision: str = "0010"
down_revision: str | None = "0009"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# Frozen copies of the types at this revision.
UTC = sa.DateTime(timezone=True)
JSON = sa.JSON().with_variant(postgresql.JSONB(), "postgresql")
# What only an answer (INFO, or any reply for last_seen_at) tells about a node.
ANSWERED_COLUMNS = (
    ("firmware", sa.String(64)),
    ("protocol_version", sa.Integer()),
    ("n_channels", sa.Integer()),
    ("fs_hz", sa.Float()),
    ("geometry", JSON),
    ("first_seen_at", UTC),
    ("last_seen_at", UTC),
)
NEVER_SEEN = "SELECT node_id FROM nodes WHERE last_seen_at IS NULL"


def upgrade() -> None:
    op.add_column("nodes", sa.Column("watched_since", UTC, nullable=True))
    op.execute("UPDATE nodes SET watched_since = first_seen_at")
    if op.get_bind().dialect.name == "sqlite":
        _sqlite_not_null(add=("watched_since",), drop=tuple(name for name, _ in ANSWERED_COLUMNS))
        return
    op.alter_column("nodes", "watched_since", existing_type=UTC, nullable=False)
    for name, type_ in ANSWERED_COLUMNS:
        op.alter_column("nodes", name, existing_type=type_, nullable=True)


def downgrade() -> None:
    op.execute(f"DELETE FROM uplink_queue WHERE node_id IN ({NEVER_SEEN})")
    op.execute(f"DELETE FROM deliveries WHERE event_id IN (SELECT id FROM events WHERE node_id IN ({NEVER_SEEN}))")
    op.execute(f"DELETE FROM events WHERE node_id IN ({NEVER_SEEN})")
    op.execute("DELETE FROM nodes WHERE last_seen_at IS NULL")
    if op.get_bind().dialect.name == "sqlite":
        _sqlite_not_null(add=tuple(name for name, _ in ANSWERED_COLUMNS), drop=("watched_since",))
        op.execute("ALTER TABLE nodes DROP COLUMN watched_since")  # SQLite 3.35+: no copy of the table
        return
    for name, type_ in reversed(ANSWERED_COLUMNS):
        op.alter_column("nodes", name, existing_type=type_, nullable=False)
    op.drop_column("nodes", "watched_since")


def _sqlite_not_null(*, add: Sequence[str], drop: Sequence[str]) -> None:
    """Add or remove NOT NULL on columns of ``nodes`` by editing its stored CREATE TABLE.

    SQLite changes a column's NOT NULL only by copying the table (batch mode), and dropping
    ``nodes`` inside the migration's transaction fails its foreign keys (measurements, events
    ... refer to it, and PRAGMA foreign_keys cannot be switched off in a transaction). Changing a
    NOT NULL leaves the file's content as it is, so SQLite documents editing the schema
    (sqlite.org/lang_altertable.html, "other kinds of table schema changes"); a NOT NULL added
    is checked against the rows first.
    """
    bind = op.get_bind()
    for name in add:
        nulls = bind.exec_driver_sql(f"SELECT count(*) FROM nodes WHERE {name} IS NULL").scalar_one()
        if nulls:
            raise RuntimeError(f"nodes.{name} is NULL in {nulls} rows: cannot make it NOT NULL")
    sql = bind.exec_driver_sql("SELECT sql FROM sqlite_schema WHERE type = 'table' AND name = 'nodes'").scalar_one()
    for name in drop:
        sql = _one_edit(sql, rf'((?:^|[(,])\s*"?{name}"?\s[^,]*?)\s+NOT NULL\b', r"\1", name)
    for name in add:
        sql = _one_edit(sql, rf'((?:^|[(,])\s*"?{name}"?\s+[A-Z]+(?:\([0-9, ]+\))?)(?=\s*(?:,|\)\s*$))',
                        r"\1 NOT NULL", name)
    version = bind.exec_driver_sql("PRAGMA schema_version").scalar_one()
    bind.exec_driver_sql("PRAGMA writable_schema = ON")
    bind.exec_driver_sql("UPDATE sqlite_schema SET sql = ? WHERE type = 'table' AND name = 'nodes'", (sql,))
    bind.exec_driver_sql(f"PRAGMA schema_version = {int(version) + 1}")
    bind.exec_driver_sql("PRAGMA writable_schema = OFF")


def _one_edit(sql: str, pattern: str, replacement: str, column: str) -> str:
    edited, count = re.subn(pattern, replacement, sql, count=1, flags=re.MULTILINE)
    if count != 1:
        raise RuntimeError(f"nodes.{column}: its definition is not where revision 0009 expects it: {sql}")
    return edited
