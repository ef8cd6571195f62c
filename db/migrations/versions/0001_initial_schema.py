"""Initial schema: nodes, measurements, DI maps, baselines, detections, state changes,
alert outbox (events, deliveries) and API keys.

Revision ID: 0001
Revises:
Create Date: 2026-11-23
"""
from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision: str = "0001"
down_revision: str | None = None
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# Frozen copies of the types at this revision; later model changes need a new revision.
BIG_ID = sa.BigInteger().with_variant(sa.Integer(), "sqlite")
UTC = sa.DateTime(timezone=True)
JSON = sa.JSON().with_variant(postgresql.JSONB(), "postgresql")
NODE_STATES = ("commissioning", "calibrating", "ok", "suspected", "damage", "no_valid_baseline")


def _one_of(column: str, values: Sequence[str], name: str) -> sa.CheckConstraint:
    listed = ", ".join(f"'{value}'" for value in values)
    return sa.CheckConstraint(f"{column} IN ({listed})", name=op.f(name))


def upgrade() -> None:
    op.create_table(
        "nodes",
        sa.Column("node_id", sa.String(64), nullable=False),
        sa.Column("port_url", sa.String(255), nullable=False),
        sa.Column("firmware", sa.String(64), nullable=False),
        sa.Column("protocol_version", sa.Integer(), nullable=False),
        sa.Column("n_channels", sa.Integer(), nullable=False),
        sa.Column("fs_hz", sa.Float(), nullable=False),
        sa.Column("geometry", JSON, nullable=False),
        sa.Column("first_seen_at", UTC, nullable=False),
        sa.Column("last_seen_at", UTC, nullable=False),
        sa.Column("online", sa.Boolean(), server_default=sa.false(), nullable=False),
        sa.Column("error_counters", JSON, nullable=False),
        sa.Column("state", sa.String(32), nullable=False),
        sa.Column("latest_di_peak", sa.Float(), nullable=True),
        sa.Column("latest_threshold", sa.Float(), nullable=True),
        sa.PrimaryKeyConstraint("node_id", name=op.f("pk_nodes")),
        _one_of("state", NODE_STATES, "ck_nodes_node_state"),
    )
    op.create_table(
        "measurements",
        sa.Column("id", BIG_ID, nullable=False),
        sa.Column("node_id", sa.String(64), nullable=False),
        sa.Column("kind", sa.String(32), nullable=False),
        sa.Column("acquired_at", UTC, nullable=False),
        sa.Column("node_measurement_id", sa.Integer(), nullable=False),
        sa.Column("temperature_c", sa.Float(), nullable=True),
        sa.Column("averaging", sa.Integer(), nullable=False),
        sa.Column("fs_hz", sa.Float(), nullable=False),
        sa.Column("t0_s", sa.Float(), nullable=False),
        sa.Column("n_channels", sa.Integer(), nullable=False),
        sa.Column("n_samples", sa.Integer(), nullable=False),
        sa.Column("volts_per_code", sa.Float(), nullable=False),
        sa.Column("excitation_hz", sa.Float(), nullable=False),
        sa.Column("cycles", sa.Integer(), nullable=False),
        sa.Column("traces_blob", sa.LargeBinary(), nullable=True),
        sa.Column("traces_codec", sa.String(32), nullable=False),
        sa.Column("traces_dtype", sa.String(8), nullable=False),
        sa.Column("traces_sha256", sa.String(64), nullable=False),
        sa.Column("traces_nbytes", sa.Integer(), nullable=False),
        sa.Column("traces_pruned_at", UTC, nullable=True),
        sa.Column("stored_at", UTC, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_measurements")),
        sa.ForeignKeyConstraint(["node_id"], ["nodes.node_id"], name=op.f("fk_measurements_node_id_nodes")),
        _one_of("kind", ("baseline", "monitor"), "ck_measurements_measurement_kind"),
        sa.CheckConstraint(
            "(traces_blob IS NULL) = (traces_pruned_at IS NOT NULL)",
            name=op.f("ck_measurements_traces_xor_pruned"),
        ),
    )
    op.create_index("ix_measurements_node_time", "measurements", ["node_id", "acquired_at", "id"])
    op.create_table(
        "di_maps",
        sa.Column("id", BIG_ID, nullable=False),
        sa.Column("measurement_id", BIG_ID, nullable=False),
        sa.Column("source", sa.String(32), nullable=False),
        sa.Column("method", sa.String(64), nullable=False),
        sa.Column("grid", JSON, nullable=False),
        sa.Column("baseline_measurement_id", BIG_ID, nullable=True),
        sa.Column("pixels_blob", sa.LargeBinary(), nullable=False),
        sa.Column("pixels_codec", sa.String(32), nullable=False),
        sa.Column("pixels_dtype", sa.String(8), nullable=False),
        sa.Column("pixels_sha256", sa.String(64), nullable=False),
        sa.Column("peak_di", sa.Float(), nullable=False),
        sa.Column("created_at", UTC, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_di_maps")),
        sa.ForeignKeyConstraint(
            ["measurement_id"], ["measurements.id"], name=op.f("fk_di_maps_measurement_id_measurements")
        ),
        sa.ForeignKeyConstraint(
            ["baseline_measurement_id"],
            ["measurements.id"],
            name=op.f("fk_di_maps_baseline_measurement_id_measurements"),
        ),
        _one_of("source", ("node", "gateway"), "ck_di_maps_map_source"),
    )
    op.create_index(op.f("ix_di_maps_measurement_id"), "di_maps", ["measurement_id"])
    op.create_table(
        "baselines",
        sa.Column("id", BIG_ID, nullable=False),
        sa.Column("node_id", sa.String(64), nullable=False),
        sa.Column("measurement_id", BIG_ID, nullable=False),
        sa.Column("created_by", sa.String(128), nullable=False),
        sa.Column("created_at", UTC, nullable=False),
        sa.Column("reason", sa.Text(), nullable=False),
        sa.Column("active", sa.Boolean(), nullable=False),
        sa.Column("deactivated_at", UTC, nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_baselines")),
        sa.ForeignKeyConstraint(["node_id"], ["nodes.node_id"], name=op.f("fk_baselines_node_id_nodes")),
        sa.ForeignKeyConstraint(
            ["measurement_id"], ["measurements.id"], name=op.f("fk_baselines_measurement_id_measurements")
        ),
    )
    op.create_index(op.f("ix_baselines_node_id"), "baselines", ["node_id"])
    op.create_index(op.f("ix_baselines_measurement_id"), "baselines", ["measurement_id"])
    op.create_index(
        "uq_baselines_one_active_per_node",
        "baselines",
        ["node_id"],
        unique=True,
        sqlite_where=sa.text("active"),
        postgresql_where=sa.text("active"),
    )
    op.create_table(
        "detections",
        sa.Column("id", BIG_ID, nullable=False),
        sa.Column("measurement_id", BIG_ID, nullable=False),
        sa.Column("node_id", sa.String(64), nullable=False),
        sa.Column("peak_di", sa.Float(), nullable=True),
        sa.Column("threshold", sa.Float(), nullable=True),
        sa.Column("axial_mm", sa.Float(), nullable=True),
        sa.Column("angle_deg", sa.Float(), nullable=True),
        sa.Column("state", sa.String(32), nullable=False),
        sa.Column("confidence", sa.Float(), nullable=True),
        sa.Column("method", sa.String(32), nullable=True),
        sa.Column("defects", JSON, nullable=True),
        sa.Column("sensor_faults", JSON, nullable=True),
        sa.Column("baseline_measurement_id", BIG_ID, nullable=True),
        sa.Column("stretch", sa.Float(), nullable=True),
        sa.Column("created_at", UTC, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_detections")),
        sa.ForeignKeyConstraint(
            ["baseline_measurement_id"],
            ["measurements.id"],
            name=op.f("fk_detections_baseline_measurement_id_measurements"),
        ),
        sa.UniqueConstraint("measurement_id", name=op.f("uq_detections_measurement_id")),
        sa.ForeignKeyConstraint(
            ["measurement_id"], ["measurements.id"], name=op.f("fk_detections_measurement_id_measurements")
        ),
        sa.ForeignKeyConstraint(["node_id"], ["nodes.node_id"], name=op.f("fk_detections_node_id_nodes")),
        _one_of("state", NODE_STATES, "ck_detections_detection_state"),
    )
    op.create_index("ix_detections_node_time", "detections", ["node_id", "created_at", "id"])
    op.create_table(
        "state_changes",
        sa.Column("id", BIG_ID, nullable=False),
        sa.Column("node_id", sa.String(64), nullable=False),
        sa.Column("measurement_id", BIG_ID, nullable=True),
        sa.Column("from_state", sa.String(32), nullable=False),
        sa.Column("to_state", sa.String(32), nullable=False),
        sa.Column("at", UTC, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_state_changes")),
        sa.ForeignKeyConstraint(["node_id"], ["nodes.node_id"], name=op.f("fk_state_changes_node_id_nodes")),
        sa.ForeignKeyConstraint(
            ["measurement_id"], ["measurements.id"], name=op.f("fk_state_changes_measurement_id_measurements")
        ),
        _one_of("from_state", NODE_STATES, "ck_state_changes_from_state"),
        _one_of("to_state", NODE_STATES, "ck_state_changes_to_state"),
    )
    op.create_index("ix_state_changes_node_time", "state_changes", ["node_id", "at", "id"])
    op.create_table(
        "events",
        sa.Column("id", sa.Uuid(), nullable=False),
        sa.Column("node_id", sa.String(64), nullable=True),
        sa.Column("kind", sa.String(64), nullable=False),
        sa.Column("severity", sa.String(32), nullable=False),
        sa.Column("payload", JSON, nullable=False),
        sa.Column("created_at", UTC, nullable=False),
        sa.Column("acknowledged_at", UTC, nullable=True),
        sa.Column("acknowledged_by", sa.String(128), nullable=True),
        sa.Column("resolved_at", UTC, nullable=True),
        sa.Column("resolved_by", sa.String(128), nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_events")),
        sa.ForeignKeyConstraint(["node_id"], ["nodes.node_id"], name=op.f("fk_events_node_id_nodes")),
        _one_of("severity", ("info", "warning", "critical"), "ck_events_severity"),
    )
    op.create_index(op.f("ix_events_node_id"), "events", ["node_id"])
    op.create_index("ix_events_created_at", "events", ["created_at"])
    op.create_table(
        "deliveries",
        sa.Column("id", BIG_ID, nullable=False),
        sa.Column("event_id", sa.Uuid(), nullable=False),
        sa.Column("sink", sa.String(64), nullable=False),
        sa.Column("status", sa.String(32), nullable=False),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("next_attempt_at", UTC, nullable=True),
        sa.Column("last_error", sa.Text(), nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_deliveries")),
        sa.UniqueConstraint("event_id", "sink", name=op.f("uq_deliveries_event_id_sink")),
        sa.ForeignKeyConstraint(["event_id"], ["events.id"], name=op.f("fk_deliveries_event_id_events")),
        _one_of("status", ("pending", "delivered", "dead"), "ck_deliveries_delivery_status"),
    )
    op.create_index("ix_deliveries_due", "deliveries", ["status", "next_attempt_at"])
    op.create_table(
        "api_keys",
        sa.Column("id", BIG_ID, nullable=False),
        sa.Column("name", sa.String(128), nullable=False),
        sa.Column("role", sa.String(32), nullable=False),
        sa.Column("key_hash", sa.String(64), nullable=False),
        sa.Column("key_prefix", sa.String(16), nullable=False),
        sa.Column("created_at", UTC, nullable=False),
        sa.Column("revoked_at", UTC, nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_api_keys")),
        sa.UniqueConstraint("key_hash", name=op.f("uq_api_keys_key_hash")),
        _one_of("role", ("viewer", "operator", "admin"), "ck_api_keys_role"),
    )


def downgrade() -> None:
    for table in (
        "api_keys",
        "deliveries",
        "events",
        "state_changes",
        "detections",
        "baselines",
        "di_maps",
        "measurements",
        "nodes",
    ):
        op.drop_table(table)
