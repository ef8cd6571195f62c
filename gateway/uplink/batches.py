"""What goes into one batch, and what the centre's answer means (pure).

A batch is a prefix of every node's part of the queue rows it is built from: it is cut at the
record count and the body size, and a node whose uid repeats (a measurement queued again with
its traces while the first is still pending) stops there until the next batch.
"""
from __future__ import annotations

import gzip
import json
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

from pydantic import ValidationError

from alerts.backoff import parse_retry_after
from gateway.uplink.records import Wire
from uplink.contract import BadRecord, IngestBatch, IngestResult, NodeRecord

BODY_OVERHEAD_BYTES = 256  # the batch's own members around its records
GZIP_LEVEL = 1  # the traces are compressed already; gzip mostly undoes base64's 4/3


@dataclass(frozen=True)
class Batch:
    batch_id: uuid.UUID
    row_ids: tuple[int, ...]  # the queue rows, in record order (records[i] is row_ids[i])
    nodes: tuple[str | None, ...]
    body: bytes  # the JSON body, uncompressed
    node_revisions: Mapping[str, int] = field(default_factory=dict)  # the revision each node record carries

    def __len__(self) -> int:
        return len(self.row_ids)

    def gzipped(self) -> bytes:
        return gzip.compress(self.body, compresslevel=GZIP_LEVEL, mtime=0)


def build_batch(
    wires: Sequence[Wire], *, gateway_id: str, site: str, max_records: int, max_bytes: int,
    batch_id: uuid.UUID | None = None,
) -> Batch | None:
    """The batch of ``wires`` (in their order) within ``max_records`` and ``max_bytes``; None if empty.

    A record bigger than ``max_bytes`` on its own goes alone (the centre may still refuse it
    with 413; the sender then sets it aside).
    """
    chosen: list[Wire] = []
    seen: set[str] = set()
    stopped: set[str | None] = set()  # nodes whose part of this batch has ended
    size = BODY_OVERHEAD_BYTES
    for wire in wires:
        if len(chosen) >= max_records:
            break
        if wire.node_id in stopped:
            continue
        if wire.record.uid in seen:
            stopped.add(wire.node_id)
            continue
        record_size = len(wire.record.model_dump_json()) + 1
        if chosen and size + record_size > max_bytes:
            break  # not `continue`: a later record of a node must not overtake this one
        chosen.append(wire)
        seen.add(wire.record.uid)
        size += record_size
    if not chosen:
        return None
    batch_id = batch_id or uuid.uuid4()
    batch = IngestBatch(gateway_id=gateway_id, site=site, batch_id=batch_id, records=[w.record for w in chosen])
    revisions = {w.record.node_id: w.record.revision for w in chosen if isinstance(w.record, NodeRecord)}
    return Batch(batch_id, tuple(w.row_id for w in chosen), tuple(w.node_id for w in chosen),
                 batch.model_dump_json().encode(), revisions)


OutcomeKind = Literal["stored", "bad_record", "too_large", "bad_batch", "retry", "misconfigured"]
RETRY_STATUSES = frozenset({408, 425, 429, 500, 502, 503, 504})


@dataclass(frozen=True)
class Outcome:
    """What the sender does next: ``stored`` (mark sent), ``bad_record`` (that record is refused),
    ``too_large`` / ``bad_batch`` (split the batch), ``retry`` (back off, the link or the centre
    is down or busy), ``misconfigured`` (back off, an operator must act: key, site, URL)."""

    kind: OutcomeKind
    detail: str
    retry_after_s: float | None = None
    bad_index: int | None = None
    result: IngestResult | None = None


def classify(status: int, headers: Mapping[str, str], body: bytes) -> Outcome:
    """The outcome of the centre's answer ``status`` with ``headers`` and ``body``."""
    if 200 <= status < 300:
        try:
            result = IngestResult.model_validate_json(body)
        except ValidationError:
            return Outcome("stored", f"HTTP {status}, an answer without the ingest result")
        return Outcome("stored", f"HTTP {status}", result=result)
    detail = f"HTTP {status}{_problem_detail(body)}"
    retry_after = parse_retry_after(headers.get("retry-after"))
    if status in RETRY_STATUSES or status >= 500:
        return Outcome("retry", detail, retry_after_s=retry_after)
    if status == 413:
        return Outcome("too_large", detail)
    if status in (409, 422):
        bad = _bad_record(body)
        if bad is not None and bad.index is not None:
            return Outcome("bad_record", f"{detail} (record {bad.index} {bad.uid}: {bad.error})", bad_index=bad.index)
        return Outcome("bad_batch", detail)
    return Outcome("misconfigured", detail, retry_after_s=retry_after)  # 401, 403, 404, ...


def _problem(body: bytes) -> dict | None:
    try:
        parsed = json.loads(body)
    except (ValueError, UnicodeDecodeError):
        return None
    return parsed if isinstance(parsed, dict) else None


def _problem_detail(body: bytes) -> str:
    problem = _problem(body)
    if problem is None:
        text = body[:200].decode("utf-8", "replace").replace("\n", " ").strip()
        return f" {text}" if text else ""
    detail = problem.get("detail") or problem.get("title")
    return f" {str(detail)[:300]}" if detail else ""


def _bad_record(body: bytes) -> BadRecord | None:
    problem = _problem(body)
    if problem is None or not isinstance(problem.get("bad_record"), dict):
        return None
    try:
        return BadRecord.model_validate(problem["bad_record"])
    except ValidationError:
        return None
