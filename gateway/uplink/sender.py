"""The uplink's sender: one thread of the gateway replicates the queue to the central PipeSentry.

Each pass reads a fair batch (``db.uplink_queue.next_batch``: every node with something pending
gets its share, in its own order), POSTs it (gzip, bounded by ``timeout_s``) and marks its
records sent only once the centre answered that it stored them (or held them already). So a
link cut, a centre stopped, a connection dropped mid-request or the gateway killed at any
moment re-sends the batch, and the centre's uids make that a duplicate, never a loss.

Failures: the link or the centre down or busy (connection errors, timeouts, 5xx, 429 and 503
with their Retry-After) are retried for as long as they last, with full-jitter exponential
backoff capped at ``backoff_cap_s`` (``retry_timing``) and never sooner than the centre's
Retry-After (itself capped): the records wait safely in the queue meanwhile. A record the
centre refuses as malformed is tried ``refusals_max`` times, then set aside (kept, counted,
logged) so it never holds its node's later records up; a batch too large (413) is halved. A
401/403/404 (wrong key, site or URL) backs off the same way and is logged as an error.

Traces on demand: every ``requests_every_s`` it also asks the centre for the trace requests of
this gateway (``GET TRACE_REQUESTS_PATH``; a site behind NAT is never called), queues each
measurement again with its traces if it still holds them (``answer_trace_request``) and answers
``held`` or ``pruned``. An answer that does not reach the centre is given again on the next poll,
and the measurement is not queued twice.

The node workers never wait on it: measuring, flagging and alerting go on with the link down.
"""
from __future__ import annotations

import logging
import random
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime
from typing import Protocol

import httpx

from db.clock import utc_now
from db.database import Database
from db.errors import StorageError
from db.uplink_queue import answer_trace_request, mark_sent, next_batch, note_refusal
from gateway.config import UplinkSettings
from gateway.uplink.batches import Batch, Outcome, build_batch, classify
from gateway.uplink.records import wire_records
from retry_timing.backoff import Backoff
from uplink.contract import (
    INGEST_PATH,
    TRACE_ANSWERS_PATH,
    TRACE_REQUESTS_PATH,
    TraceAnswer,
    TraceAnswers,
    TraceRequests,
)

log = logging.getLogger("pipesentry.uplink")

UPLINK = "uplink"  # the thread's name and heartbeat
USER_AGENT = "PipeSentry-Uplink/1"


class UplinkKeyError(ValueError):
    """The uplink's key cannot be read (its file went away or was emptied since the config was checked)."""


@dataclass
class UplinkStats:
    """What the sender did since the process started (the gateway's metrics read it)."""

    batches: int = 0  # batches the centre stored
    records: int = 0  # records in them (accepted or duplicates)
    accepted: int = 0  # of which new at the centre
    duplicates: int = 0  # of which the centre already held (a batch re-sent after a lost answer)
    failures: int = 0  # POSTs that did not store their batch
    refused: int = 0  # records set aside as refused
    consecutive_failures: int = 0
    last_stored_at: datetime | None = None
    last_error: str | None = None
    # The centre's trace requests answered, by answer (held or pruned).
    trace_answers: dict[str, int] = field(default_factory=lambda: {"held": 0, "pruned": 0})
    requests_failures: int = 0  # polls for trace requests, or deliveries of their answers, that failed
    last_requests_error: str | None = None  # why the last poll for trace requests failed (None: it did not)


class Beats(Protocol):
    def beat(self, name: str) -> None: ...


class UplinkSender:
    """Sends the uplink queue to ``settings.url`` until ``stop`` is set."""

    def __init__(
        self,
        settings: UplinkSettings,
        database: Database,
        *,
        stop: threading.Event,
        heartbeats: Beats | None = None,
        rng: random.Random | None = None,
        clock: Callable[[], datetime] = utc_now,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        self.settings = settings
        self.database = database
        self.stop = stop
        self.heartbeats = heartbeats
        self.rng = rng or random.Random()
        self.clock = clock
        self.stats = UplinkStats()
        self.backoff = Backoff(settings.backoff_base_s, settings.backoff_cap_s, "full")
        self.limit = settings.batch_records  # halved after a 413 or a malformed batch, grows back after a stored one
        self.after_node: str | None = None  # the node the last batch started with: the next starts after it
        self.endpoint = settings.url.rstrip("/") + INGEST_PATH
        self.requests_endpoint = settings.url.rstrip("/") + TRACE_REQUESTS_PATH
        self.answers_endpoint = settings.url.rstrip("/") + TRACE_ANSWERS_PATH
        self.monotonic = time.monotonic
        self.requests_due_at = 0.0  # the first pass asks at once
        try:
            key = settings.read_key()
        except ValueError as exc:
            raise UplinkKeyError(str(exc)) from None
        self.client = httpx.Client(
            timeout=httpx.Timeout(settings.timeout_s),
            follow_redirects=False,
            trust_env=False,  # the centre is addressed directly, never through an ambient proxy
            headers={"User-Agent": USER_AGENT, "Authorization": f"Bearer {key}"},
            transport=transport,
        )
        self.thread = threading.Thread(target=self.run, name=UPLINK, daemon=True)

    def stall_limit_s(self) -> float:
        """The longest a healthy pass and its wait can take: a request, the longest wait, slack."""
        s = self.settings
        return 3 * (s.timeout_s + max(s.backoff_cap_s, s.retry_after_max_s, s.idle_s)) + 60.0

    def run(self) -> None:
        try:
            while not self.stop.is_set():
                if self.heartbeats is not None:
                    self.heartbeats.beat(UPLINK)
                try:
                    if self.monotonic() >= self.requests_due_at:
                        self.requests_due_at = self.monotonic() + self.settings.requests_every_s
                        self.poll_requests()
                    wait_s = self.run_once()
                except StorageError as exc:
                    log.error("uplink: storage unavailable, will retry in %.1f s: %s", self.settings.idle_s, exc)
                    wait_s = self.settings.idle_s
                except Exception:  # a bug must not end replication; logged with its traceback, then retried
                    log.exception("uplink: unexpected error, will retry in %.1f s", self.settings.idle_s)
                    wait_s = self.settings.idle_s
                if wait_s > 0 and self.stop.wait(wait_s):
                    break
        finally:
            self.client.close()

    def run_once(self) -> float:
        """One batch: read, send, record. Returns the seconds to wait before the next pass."""
        s = self.settings
        with self.database.session() as session:
            rows = next_batch(session, limit=self.limit, after_node=self.after_node)
            wires, unreadable = wire_records(session, s.gateway_id, rows)
        if unreadable:
            self._set_aside(unreadable)
        batch = build_batch(wires, gateway_id=s.gateway_id, site=s.site, max_records=self.limit,
                            max_bytes=s.batch_bytes)
        if batch is None:
            return 0.0 if unreadable else s.idle_s
        self.after_node = batch.nodes[0] or ""
        outcome = self._post(batch)
        return self._record(batch, outcome)

    def poll_requests(self) -> int:
        """Ask the centre for its trace requests, act on them and answer; returns how many were answered.

        A failure (link down, an older centre without the route) is logged and left for the next poll.
        """
        s = self.settings
        try:
            response = self.client.get(self.requests_endpoint, params={"gateway_id": s.gateway_id})
            if response.status_code != 200:
                return self._requests_failed(f"HTTP {response.status_code} {response.text[:200]}")
            requests = TraceRequests.model_validate_json(response.content)
        except httpx.HTTPError as exc:
            return self._requests_failed(f"{type(exc).__name__}: {exc}")
        except ValueError as exc:  # pydantic's ValidationError is one
            return self._requests_failed(f"an answer that is not a list of trace requests: {exc}")
        if not requests.items:
            self.stats.last_requests_error = None
            return 0
        answers = []
        with self.database.write() as session:
            for item in requests.items:
                answer = answer_trace_request(session, s.gateway_id, item.measurement_uid, now=self.clock())
                answers.append(TraceAnswer(request_id=item.request_id, measurement_uid=item.measurement_uid,
                                           answer=answer))
        body = TraceAnswers(gateway_id=s.gateway_id, site=s.site, answers=answers).model_dump_json()
        try:
            response = self.client.post(self.answers_endpoint, content=body,
                                        headers={"Content-Type": "application/json"})
        except httpx.HTTPError as exc:
            return self._requests_failed(f"answers not delivered: {type(exc).__name__}: {exc}")
        if response.status_code != 200:
            return self._requests_failed(f"answers not taken: HTTP {response.status_code} {response.text[:200]}")
        self.stats.last_requests_error = None
        for given in answers:
            self.stats.trace_answers[given.answer] = self.stats.trace_answers.get(given.answer, 0) + 1
            log.info("uplink: the centre asked for the traces of %s: %s", given.measurement_uid, given.answer)
        return len(answers)

    def _requests_failed(self, why: str) -> int:
        self.stats.requests_failures += 1
        self.stats.last_requests_error = why
        log.warning("uplink: trace requests not handled, asking again in %.0f s: %s",
                    self.settings.requests_every_s, why)
        return 0

    def _post(self, batch: Batch) -> Outcome:
        try:
            response = self.client.post(
                self.endpoint, content=batch.gzipped(),
                headers={"Content-Type": "application/json", "Content-Encoding": "gzip"},
            )
        except httpx.TimeoutException as exc:
            return Outcome("retry", f"timed out after {self.settings.timeout_s:g} s ({type(exc).__name__})")
        except httpx.HTTPError as exc:
            return Outcome("retry", f"{type(exc).__name__}: {exc}")
        return classify(response.status_code, response.headers, response.content)

    def _record(self, batch: Batch, outcome: Outcome) -> float:
        s = self.settings
        if outcome.kind == "stored":
            with self.database.write() as session:
                mark_sent(session, batch.row_ids, now=self.clock(), node_revisions=batch.node_revisions)
            self._stored(batch, outcome)
            return 0.0  # more may be waiting: look again at once
        self.stats.failures += 1
        self.stats.last_error = outcome.detail
        if outcome.kind == "bad_record" and outcome.bad_index is not None and outcome.bad_index < len(batch):
            self._refused(batch.row_ids[outcome.bad_index], outcome.detail)
            return 0.0
        if outcome.kind in ("too_large", "bad_batch"):
            if len(batch) == 1:
                self._refused(batch.row_ids[0], outcome.detail)
            else:
                self.limit = max(1, len(batch) // 2)
                log.warning("uplink: the centre refused a batch of %d records (%s); trying %d at a time",
                            len(batch), outcome.detail, self.limit)
            return 0.0
        self.stats.consecutive_failures += 1
        tries = self.stats.consecutive_failures
        wait_s = self.backoff.delay_s(tries, self.rng)
        if outcome.retry_after_s is not None:
            wait_s = max(wait_s, min(outcome.retry_after_s, s.retry_after_max_s))
        level = logging.ERROR if outcome.kind == "misconfigured" else logging.WARNING
        log.log(level, "uplink: batch of %d records not stored (try %d): %s; retrying in %.1f s",
                len(batch), tries, outcome.detail, wait_s)
        return wait_s

    def _stored(self, batch: Batch, outcome: Outcome) -> None:
        stats = self.stats
        if stats.consecutive_failures:
            log.info("uplink: the centre stores again after %d failed tries", stats.consecutive_failures)
        stats.consecutive_failures = 0
        stats.batches += 1
        stats.records += len(batch)
        if outcome.result is not None:
            stats.accepted += outcome.result.accepted
            stats.duplicates += outcome.result.duplicates
        stats.last_stored_at = self.clock()
        stats.last_error = None
        self.limit = min(self.settings.batch_records, self.limit * 2)
        log.debug("uplink: batch %s stored: %d records (%s)", batch.batch_id, len(batch), outcome.detail)

    def _refused(self, row_id: int, error: str) -> None:
        with self.database.write() as session:
            gave_up = note_refusal(session, row_id, error, give_up_after=self.settings.refusals_max)
        if gave_up:
            self.stats.refused += 1
            log.error("uplink: queue record %d set aside after %d refusals: %s", row_id, self.settings.refusals_max,
                      error)
        else:
            log.warning("uplink: the centre refused queue record %d: %s", row_id, error)

    def _set_aside(self, unreadable: dict[int, str]) -> None:
        with self.database.write() as session:
            for row_id, why in unreadable.items():
                note_refusal(session, row_id, f"unreadable here: {why}", give_up_after=1)
        self.stats.refused += len(unreadable)
        for row_id, why in unreadable.items():
            log.error("uplink: queue record %d set aside, it cannot be sent: %s", row_id, why)
