"""The uplink queue: what a gateway still has to replicate to the central PipeSentry.

The same outbox discipline as alert delivery: a record is queued in the transaction that
writes the fact it replicates (``store_cycle`` for a measurement and everything decided about
it, ``upsert_node`` for a node's identity, ``add_event`` for an alert event, and what an
operator changes: a node's details and (re)commissioning, a baseline set or added), so a fact is
either stored and queued or neither. It is marked ``sent`` only after the centre acknowledged
it, so a crash at any point re-sends (the centre de-duplicates by the record's uid) and never
loses anything.

Queueing is switched on by the gateway (:meth:`db.database.Database.queue_uplink`, which it calls
at start with the policy of its ``[uplink]``, or None): its own handle knows, and the choice is
stored in the database (``uplink_config``) for every other process writing it (the gateway's
API). A gateway without an uplink writes no queue. What a record carries is decided here (:func:`traces_go_up`, pure); what it looks like
on the wire is the sender's business (``gateway/uplink``).

Order and fairness (:func:`next_batch`): each node's records go in ``id`` order (the order they
were written); a batch takes an equal share from every node with something pending, starting
after the node the previous batch started with, so one node's backlog never starves another
node's live records.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, Literal, cast

from sqlalchemy import CursorResult, Result, case, func, or_, select, update
from sqlalchemy.orm import Session

from db.clock import utc_now
from db.models import (
    BaselineRow,
    EventRow,
    MeasurementKind,
    MeasurementRow,
    NodeRow,
    NodeState,
    UplinkConfigRow,
    UplinkKind,
    UplinkRow,
    UplinkStatus,
)

QUEUE_POLICY = "pipesentry.uplink_queue"  # key of Session.info: the QueuePolicy of sessions that queue
FLAGGED_STATES = frozenset({NodeState.SUSPECTED, NodeState.DAMAGE})
NO_NODE = ""  # the group of gateway-wide alert events (node_id NULL)

Send = Literal["everything", "flagged_traces"]


@dataclass(frozen=True)
class QueuePolicy:
    """What the gateway replicates: ``everything`` (every measurement with its traces) or
    ``flagged_traces`` (every record, but a measurement's traces only when it was flagged,
    is a baseline, or is asked for on demand)."""

    send: Send = "everything"


def queue_policy(session: Session) -> QueuePolicy | None:
    """The policy of a session that queues for the uplink; None when it does not queue.

    A handle the gateway told (:meth:`db.database.Database.queue_uplink`, with a policy or None)
    knows it; any other handle on the database (the gateway's API) reads the gateway's choice
    from ``uplink_config``, in the session's transaction, so an operator's change is queued
    exactly when the gateway replicates.
    """
    if QUEUE_POLICY in session.info:
        policy = session.info[QUEUE_POLICY]
        return policy if isinstance(policy, QueuePolicy) else None
    stored = session.get(UplinkConfigRow, 1)
    if stored is None or stored.send not in ("everything", "flagged_traces"):
        return None
    return QueuePolicy(cast(Send, stored.send))


def store_policy(session: Session, policy: QueuePolicy | None, *, now: datetime | None = None) -> None:
    """Record in the database whether (and how) its gateway replicates: every process writing it queues
    accordingly (``queue_policy``). The gateway calls it at start, with None when it has no uplink."""
    stored = session.get(UplinkConfigRow, 1)
    if policy is None:
        if stored is not None:
            session.delete(stored)
    elif stored is None:
        session.add(UplinkConfigRow(id=1, send=policy.send, since=now or utc_now()))
    elif stored.send != policy.send:
        stored.send, stored.since = policy.send, now or utc_now()
    session.flush()


def traces_go_up(
    policy: QueuePolicy,
    *,
    kind: MeasurementKind,
    detection_state: NodeState | None,
    peak_di: float | None,
    threshold: float | None,
    to_state: NodeState | None,
    becomes_baseline: bool,
) -> bool:
    """Whether a measurement's record carries its raw traces (pure).

    Under ``flagged_traces``: a measurement flagged (its DI peak at or above the threshold, or
    its node suspected or damaged by it), and a baseline (a flagged map cannot be reproduced at
    the centre without the traces it was computed against).
    """
    if policy.send == "everything":
        return True
    if kind == MeasurementKind.BASELINE or becomes_baseline:
        return True
    if peak_di is not None and threshold is not None and peak_di >= threshold:
        return True
    return detection_state in FLAGGED_STATES or to_state in FLAGGED_STATES


def enqueue(
    session: Session,
    kind: UplinkKind,
    ref: str | int,
    *,
    node_id: str | None,
    measurement_id: int | None = None,
    with_traces: bool = False,
    now: datetime | None = None,
) -> UplinkRow:
    """Queue one record (inside the transaction writing the fact it replicates)."""
    row = UplinkRow(
        kind=kind,
        node_id=node_id,
        ref=str(ref),
        measurement_id=measurement_id,
        with_traces=with_traces,
        created_at=now or utc_now(),
        status=UplinkStatus.PENDING,
        refusals=0,
    )
    session.add(row)
    return row


def enqueue_node(session: Session, node_id: str, *, now: datetime | None = None, first_answer: bool = False) -> bool:
    """Queue the node's identity and geometry unless a record of it is still pending (it is read
    when sent, so one pending record carries the latest); True if one was queued.

    The node's first record ever (its database predates the uplink) is followed by the node's
    baselines stored before: later records refer to them (a detection to the baseline it was
    imaged against), and the centre accepts a reference only to a record it holds. At the node's
    ``first_answer`` (registered from the configuration, never seen until now) the alert events
    stored about it meanwhile follow its record (``add_event`` held them back).
    """
    statuses = select(UplinkRow.status).where(UplinkRow.node_id == node_id, UplinkRow.kind == UplinkKind.NODE)
    queued = False
    if session.scalar(statuses.where(UplinkRow.status == UplinkStatus.PENDING).limit(1)) is None:
        first = session.scalar(statuses.limit(1)) is None
        enqueue(session, UplinkKind.NODE, node_id, node_id=node_id, now=now)
        if first:
            _enqueue_earlier_baselines(session, node_id, now=now)
        queued = True
    if first_answer:
        _enqueue_held_events(session, node_id, now=now)
    return queued


def enqueue_node_change(session: Session, node_id: str, *, now: datetime | None = None) -> bool:
    """An admin changed what the node's record carries (details, (re)commissioning): its record is
    queued as :func:`enqueue_node` does, when the session queues at all and the node has answered
    (a node never seen has no record yet; its first INFO's carries the change). True if queued."""
    if queue_policy(session) is None:
        return False
    never_answered = session.scalar(select(NodeRow.first_seen_at).where(NodeRow.node_id == node_id)) is None
    return False if never_answered else enqueue_node(session, node_id, now=now)


def enqueue_baselines(
    session: Session, node_id: str, baselines: Sequence[BaselineRow], *, now: datetime | None = None,
) -> None:
    """Queue these baseline records of the node (a new one, and those it deactivated), in order.

    Nothing before the node's first record: that one brings every baseline stored until then
    (:func:`enqueue_node`). A baseline's measurement must be at the centre with its traces (a map
    made against it can only be reproduced with them): unless a record of it that carries them is
    queued or sent, it is queued again with them first (the centre adds traces to a measurement it
    holds without, or stores it new).
    """
    if queue_policy(session) is None or not baselines:
        return
    node_queued = session.scalar(
        select(UplinkRow.id).where(UplinkRow.node_id == node_id, UplinkRow.kind == UplinkKind.NODE).limit(1)
    )
    if node_queued is None:
        return
    for baseline in baselines:
        with_traces = session.scalar(
            select(UplinkRow.id).where(
                UplinkRow.measurement_id == baseline.measurement_id, UplinkRow.kind == UplinkKind.MEASUREMENT,
                UplinkRow.with_traces.is_(True), UplinkRow.status != UplinkStatus.REFUSED,
            ).limit(1)
        )
        if with_traces is None:
            pruned = session.scalar(
                select(MeasurementRow.traces_pruned_at).where(MeasurementRow.id == baseline.measurement_id)
            )
            enqueue(session, UplinkKind.MEASUREMENT, baseline.measurement_id, node_id=node_id,
                    measurement_id=baseline.measurement_id, with_traces=pruned is None, now=now)
        enqueue(session, UplinkKind.BASELINE, baseline.id, node_id=node_id, measurement_id=baseline.measurement_id,
                now=now)


def _enqueue_held_events(session: Session, node_id: str, *, now: datetime | None) -> None:
    """The node's alert events not in the queue (stored while it had never answered), oldest first."""
    queued = select(UplinkRow.ref).where(UplinkRow.node_id == node_id, UplinkRow.kind == UplinkKind.ALERT_EVENT)
    held = session.scalars(
        select(EventRow.id).where(EventRow.node_id == node_id).order_by(EventRow.created_at, EventRow.id)
    ).all()
    already = set(session.scalars(queued))
    for event_id in held:
        if event_id.hex not in already:
            enqueue(session, UplinkKind.ALERT_EVENT, event_id.hex, node_id=node_id, now=now)


def _enqueue_earlier_baselines(session: Session, node_id: str, *, now: datetime | None) -> None:
    """The node's baseline measurements (with their traces) and baseline records, oldest first."""
    ever_baseline = select(BaselineRow.measurement_id).where(BaselineRow.node_id == node_id)
    measurement_ids = session.scalars(
        select(MeasurementRow.id)
        .where(MeasurementRow.node_id == node_id,
               or_(MeasurementRow.kind == MeasurementKind.BASELINE, MeasurementRow.id.in_(ever_baseline)))
        .order_by(MeasurementRow.id)
    ).all()
    for measurement_id in measurement_ids:
        enqueue(session, UplinkKind.MEASUREMENT, measurement_id, node_id=node_id, measurement_id=measurement_id,
                with_traces=True, now=now)
    for baseline_id, measurement_id in session.execute(
        select(BaselineRow.id, BaselineRow.measurement_id).where(BaselineRow.node_id == node_id).order_by(BaselineRow.id)
    ).all():
        enqueue(session, UplinkKind.BASELINE, baseline_id, node_id=node_id, measurement_id=measurement_id, now=now)


def request_traces(session: Session, measurement_id: int, node_id: str, *, now: datetime | None = None) -> UplinkRow:
    """On demand: queue the measurement again, this time with its traces (the centre keeps its
    record and adds the traces). The caller checks the traces are still held."""
    return enqueue(
        session, UplinkKind.MEASUREMENT, measurement_id, node_id=node_id, measurement_id=measurement_id,
        with_traces=True, now=now,
    )


def answer_trace_request(
    session: Session, gateway_id: str, measurement_uid: str, *, now: datetime | None = None,
) -> Literal["held", "pruned"]:
    """The centre asks for a measurement's traces (call inside ``Database.write()``): ``held`` when
    they are still here, with the measurement queued again with them unless a record that carries
    them is pending already (so a request asked twice queues once); ``pruned`` when retention
    removed them, or the uid names no measurement of this gateway's."""
    prefix = f"{gateway_id}/measurement/"
    local = measurement_uid.removeprefix(prefix)
    if local == measurement_uid or not local.isdigit():
        return "pruned"
    measurement_id = int(local)
    found = session.execute(
        select(MeasurementRow.node_id, MeasurementRow.traces_pruned_at).where(MeasurementRow.id == measurement_id)
    ).first()
    if found is None or found.traces_pruned_at is not None:
        return "pruned"
    queued = session.scalar(
        select(UplinkRow.id).where(UplinkRow.measurement_id == measurement_id, UplinkRow.kind == UplinkKind.MEASUREMENT,
                                   UplinkRow.with_traces.is_(True), UplinkRow.status == UplinkStatus.PENDING).limit(1)
    )
    if queued is None:
        request_traces(session, measurement_id, found.node_id, now=now)
    return "held"


# ------------------------------------------------------------------ the sender's side
def next_batch(session: Session, *, limit: int, after_node: str | None = None) -> list[UplinkRow]:
    """Up to ``limit`` pending records: an equal share of each node's oldest (``id`` order).

    Nodes take turns from the one after ``after_node`` (the previous batch's first node, in
    node-id order, wrapping round); within the batch the records go round the nodes (each
    node's first, then each node's second, ...), so a cut anywhere leaves every node's part
    a prefix of its queue.
    """
    if limit < 1:
        raise ValueError(f"limit must be >= 1, got {limit}")
    group = func.coalesce(UplinkRow.node_id, NO_NODE)
    nodes = list(session.scalars(
        select(group).where(UplinkRow.status == UplinkStatus.PENDING).group_by(group).order_by(group)
    ))
    if not nodes:
        return []
    turn = rotate(nodes, after_node)
    share = max(1, -(-limit // len(turn)))  # ceil: the share of each node, the batch is cut at limit
    rank = func.row_number().over(partition_by=group, order_by=UplinkRow.id).label("rank")
    ranked = (
        select(UplinkRow.id.label("row_id"), group.label("grp"), rank)
        .where(UplinkRow.status == UplinkStatus.PENDING)
        .subquery()
    )
    position = case({node: index for index, node in enumerate(turn)}, value=ranked.c.grp, else_=len(turn))
    ids = list(session.scalars(
        select(ranked.c.row_id)
        .where(ranked.c.rank <= share)
        .order_by(ranked.c.rank, position)
        .limit(limit)
    ))
    rows = {row.id: row for row in session.scalars(select(UplinkRow).where(UplinkRow.id.in_(ids)))}
    return [rows[i] for i in ids]


def rotate(nodes: Sequence[str], after: str | None) -> list[str]:
    """``nodes`` (sorted) starting with the first one after ``after``, wrapping round (pure)."""
    if after is None:
        return list(nodes)
    start = next((i for i, node in enumerate(nodes) if node > after), 0)
    return [*nodes[start:], *nodes[:start]]


def mark_sent(
    session: Session, ids: Sequence[int], *, now: datetime | None = None, node_revisions: Mapping[str, int] | None = None,
) -> int:
    """The centre acknowledged these records; returns how many were still pending.

    ``node_revisions``: the revision each node record of the batch carried. A node changed since
    its record was read (an admin's change committed while the batch was on its way found that
    record pending and queued none) is queued again, so no change is left behind.
    """
    if not ids:
        return 0
    result = session.execute(
        update(UplinkRow)
        .where(UplinkRow.id.in_(list(ids)), UplinkRow.status == UplinkStatus.PENDING)
        .values(status=UplinkStatus.SENT, sent_at=now or utc_now(), last_error=None)
        .execution_options(synchronize_session=False)
    )
    for node_id, sent_revision in (node_revisions or {}).items():
        revision = session.scalar(select(NodeRow.revision).where(NodeRow.node_id == node_id))
        if revision is not None and revision > sent_revision:
            enqueue_node(session, node_id, now=now)
    return _affected(result)


def note_refusal(session: Session, record_id: int, error: str, *, give_up_after: int) -> bool:
    """The centre refused the record as malformed: counted; after ``give_up_after`` refusals it is
    ``refused`` and no longer holds its node's queue up. Returns True when it was given up on."""
    row = session.get(UplinkRow, record_id)
    if row is None or row.status != UplinkStatus.PENDING:
        return False
    row.refusals += 1
    row.last_error = error[:2000]
    if row.refusals >= give_up_after:
        row.status = UplinkStatus.REFUSED
    session.flush()
    return row.status == UplinkStatus.REFUSED


# ------------------------------------------------------------------ read side (/metrics, readiness)
@dataclass(frozen=True)
class QueueStats:
    depth: int  # records not yet acknowledged by the centre
    oldest_pending_at: datetime | None  # when the oldest of them was queued
    refused: int  # records the centre refused (kept here)

    def lag_s(self, now: datetime) -> float:
        """Seconds the oldest unsent record has waited (0 when nothing waits)."""
        if self.oldest_pending_at is None:
            return 0.0
        return max(0.0, (now - self.oldest_pending_at).total_seconds())


def queue_stats(session: Session) -> QueueStats:
    depth, oldest = session.execute(
        select(func.count(), func.min(UplinkRow.created_at)).where(UplinkRow.status == UplinkStatus.PENDING)
    ).one()
    refused = session.scalar(
        select(func.count()).select_from(UplinkRow).where(UplinkRow.status == UplinkStatus.REFUSED)
    )
    return QueueStats(int(depth or 0), _aware(oldest) if oldest is not None else None, int(refused or 0))


def unsent_traces() -> Any:
    """The measurements whose traces a record still has to carry (retention keeps them)."""
    return select(UplinkRow.measurement_id).where(
        UplinkRow.with_traces.is_(True), UplinkRow.status != UplinkStatus.SENT, UplinkRow.measurement_id.is_not(None)
    )


def _aware(value: datetime | str) -> datetime:
    # min() over the column comes back untyped on SQLite (naive UTC text).
    if isinstance(value, str):
        value = datetime.fromisoformat(value)
    return value if value.tzinfo is not None else value.replace(tzinfo=UTC)


def _affected(result: Result[Any]) -> int:
    return cast(CursorResult[Any], result).rowcount
