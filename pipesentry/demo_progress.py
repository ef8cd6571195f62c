"""The demo's view of the database: state changes as they happen and a periodic status line per node."""
from __future__ import annotations

import math
from collections.abc import Callable

from sqlalchemy import func, select

from db.database import Database, open_database
from db.errors import SchemaOutOfDate, StorageError
from db.models import DetectionRow, MeasurementRow, NodeRow, StateChangeRow

STATUS_EVERY_S = 10.0


def _fmt(value: float | None, spec: str = ".3g") -> str:
    return "-" if value is None else format(value, spec)


class Progress:
    """Follows a gateway database read-only and prints what changed."""

    def __init__(
        self,
        url: str,
        truths: dict[str, list[tuple[float, float, float]]],
        echo: Callable[[str], None] = print,
        circumference_mm: float = math.pi * 114.6,
    ) -> None:
        self.url = url
        self.truths = truths
        self.echo = echo
        self.circumference_mm = circumference_mm
        self._db: Database | None = None
        self._last_change_id = 0
        self._last_status_s = -math.inf

    def _database(self) -> Database | None:
        if self._db is None:
            try:
                self._db = open_database(self.url, upgrade=False)
            except (SchemaOutOfDate, StorageError):
                return None  # the gateway is still creating the schema
        return self._db

    def _error_mm(self, node_id: str, axial_mm: float | None, angle_deg: float | None, elapsed_s: float) -> str:
        if axial_mm is None or angle_deg is None:
            return ""
        present = [(a, g) for a, g, t in self.truths.get(node_id, []) if t <= elapsed_s]
        if not present:
            return ""
        best = min(
            math.hypot(axial_mm - a, min(abs(angle_deg - g) % 360, 360 - abs(angle_deg - g) % 360) * self.circumference_mm / 360)
            for a, g in present
        )
        a, g = present[0]
        return f"; truth {a:.0f} mm, {g:.0f} deg, error {best:.1f} mm"

    def poll(self, elapsed_s: float) -> None:
        db = self._database()
        if db is None:
            return
        try:
            with db.session() as s:
                changes = s.execute(
                    select(StateChangeRow, DetectionRow)
                    .outerjoin(DetectionRow, DetectionRow.measurement_id == StateChangeRow.measurement_id)
                    .where(StateChangeRow.id > self._last_change_id)
                    .order_by(StateChangeRow.id)
                ).all()
                for change, det in changes:
                    self._last_change_id = change.id
                    where = ""
                    if det is not None and det.axial_mm is not None:
                        where = (f" — peak DI {_fmt(det.peak_di)} vs threshold {_fmt(det.threshold)}, "
                                 f"estimate {det.axial_mm:.1f} mm, {det.angle_deg:.1f} deg"
                                 + self._error_mm(change.node_id, det.axial_mm, det.angle_deg, elapsed_s))
                    self.echo(f"[{elapsed_s:5.0f} s] {change.node_id}: {change.from_state.value} -> "
                              f"{change.to_state.value}{where}")
                if elapsed_s - self._last_status_s >= STATUS_EVERY_S:
                    self._last_status_s = elapsed_s
                    for line in self._status_lines(s, elapsed_s):
                        self.echo(line)
        except StorageError as exc:
            self.echo(f"(database busy: {exc})")

    def _status_lines(self, s, elapsed_s: float) -> list[str]:
        counts = dict(s.execute(select(MeasurementRow.node_id, func.count()).group_by(MeasurementRow.node_id)).all())
        lines = []
        for node in s.scalars(select(NodeRow).order_by(NodeRow.node_id)).all():
            det = s.scalars(
                select(DetectionRow).where(DetectionRow.node_id == node.node_id).order_by(DetectionRow.id.desc())
            ).first()
            est = ""
            if det is not None and det.axial_mm is not None:
                est = f", estimate {det.axial_mm:.0f} mm {det.angle_deg:.0f} deg"
            lines.append(
                f"[{elapsed_s:5.0f} s] {node.node_id}: {node.state.value:<13} {counts.get(node.node_id, 0):3d} measurements, "
                f"peak DI {_fmt(node.latest_di_peak)} / threshold {_fmt(node.latest_threshold)}{est}"
            )
        return lines

    def summary(self) -> None:
        db = self._database()
        if db is None:
            self.echo("no measurement was stored")
            return
        with db.session() as s:
            self.echo("\nsummary:")
            for line in self._status_lines(s, math.inf):
                self.echo(line.replace("[  inf s] ", "  "))
            for node in s.scalars(select(NodeRow).order_by(NodeRow.node_id)).all():
                det = s.scalars(
                    select(DetectionRow).where(DetectionRow.node_id == node.node_id).order_by(DetectionRow.id.desc())
                ).first()
                if det is not None and self.truths.get(node.node_id):
                    err = self._error_mm(node.node_id, det.axial_mm, det.angle_deg, math.inf)
                    if err:
                        self.echo(f"  {node.node_id}: last estimate{err}")
        db.dispose()
