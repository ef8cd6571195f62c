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
                    if det is not None and det.axial_mm is not None and det.angle_deg is not None:
                        where = f" — peak DI {_fmt(det.peak_di)} vs threshold {_fmt(det.threshold)}, "
                        if det.defects:
                            where += (f"estimate {det.axial_mm:.1f} mm, {det.angle_deg:.1f} deg"
                                      + self._error_mm(change.node_id, det.axial_mm, det.angle_deg, elapsed_s))
                        else:  # nothing above the threshold: the peak is noise, no position to judge
                            where += f"map peak {det.axial_mm:.0f} mm, {det.angle_deg:.0f} deg"
                    self.echo(f"[{elapsed_s:5.0f} s] {change.node_id}: {change.from_state.value} -> "
                              f"{change.to_state.value}{where}")
                if elapsed_s - self._last_status_s >= STATUS_EVERY_S:
                    self._last_status_s = elapsed_s
                    for line in self._status_lines(s, elapsed_s):
                        self.echo(line)
        except StorageError as exc:
            self.echo(f"(database busy: {exc})")

    def _status_lines(self, s, elapsed_s: float, prefix: str | None = None) -> list[str]:
        counts = dict(s.execute(select(MeasurementRow.node_id, func.count()).group_by(MeasurementRow.node_id)).all())
        lines = []
        for node in s.scalars(select(NodeRow).order_by(NodeRow.node_id)).all():
            det = self._latest_detection(s, node.node_id)
            est = ""
            if det is not None and det.axial_mm is not None:
                # Below the threshold the map's peak is noise, not a defect's position.
                what = "estimate" if det.defects else "map peak"
                est = f", {what} {det.axial_mm:.0f} mm {det.angle_deg:.0f} deg"
            lines.append(
                f"{prefix if prefix is not None else f'[{elapsed_s:5.0f} s]'} {node.node_id}: "
                f"{node.state.value:<13} {counts.get(node.node_id, 0):3d} measurements, "
                f"peak DI {_fmt(node.latest_di_peak)} / threshold {_fmt(node.latest_threshold)}{est}"
            )
        return lines

    @staticmethod
    def _latest_detection(s, node_id: str) -> DetectionRow | None:
        return s.scalars(
            select(DetectionRow).where(DetectionRow.node_id == node_id).order_by(DetectionRow.id.desc())
        ).first()

    def verdict(self, node_id: str, det: DetectionRow | None, elapsed_s: float) -> str | None:
        """The summary's line about a node's simulated defects: found where, missed, or not there yet."""
        truths = self.truths.get(node_id, [])
        if not truths:
            return None
        present = [(a, g) for a, g, t in truths if t <= elapsed_s]
        if not present:
            first_s = min(t for _, _, t in truths)
            return f"  {node_id}: its defect appears {first_s:.0f} s in; the demo stopped at {elapsed_s:.0f} s"
        if det is None or not det.defects or det.axial_mm is None:
            a, g = present[0]
            return f"  {node_id}: defect at {a:.0f} mm, {g:.0f} deg not flagged (yet)"
        return f"  {node_id}: last estimate{self._error_mm(node_id, det.axial_mm, det.angle_deg, elapsed_s)}"

    def summary(self, elapsed_s: float) -> None:
        db = self._database()
        if db is None:
            self.echo("no measurement was stored")
            return
        try:
            with db.session() as s:
                self.echo("\nsummary:")
                for line in self._status_lines(s, elapsed_s, prefix=" "):
                    self.echo(line)
                for node in s.scalars(select(NodeRow).order_by(NodeRow.node_id)).all():
                    verdict = self.verdict(node.node_id, self._latest_detection(s, node.node_id), elapsed_s)
                    if verdict:
                        self.echo(verdict)
        finally:
            db.dispose()
