"""Ingest of gateways' batches: the body undone and bounded, the batch parsed, stored whole, the answer.

Pure helpers for the decisions (how big, which record is bad) and one function that runs in a
worker thread with the database (``store``). The route (``service/routes/ingest.py``) adds the
key's scope and the concurrency bound.
"""
from __future__ import annotations

import json
import logging
import zlib
from typing import Any

from pydantic import ValidationError
from sqlalchemy import exc as sa_exc

from db.database import Database
from db.ingest import IngestOutcome, IngestRefused, ingest_batch
from db.trace_requests import refuse_resent
from uplink.contract import IngestBatch

log = logging.getLogger("pipesentry.api")


class BodyTooLarge(Exception):
    """The body, once gzip is undone, is over the limit."""


class BodyUnreadable(Exception):
    """A Content-Encoding we do not take, or gzip that does not inflate."""


def undo_content_encoding(body: bytes, encoding: str | None, *, max_bytes: int) -> bytes:
    """The JSON bytes of the request; gzip inflated at most to ``max_bytes`` (a bomb stops there)."""
    encoding = (encoding or "identity").strip().lower()
    if encoding == "identity":
        if len(body) > max_bytes:
            raise BodyTooLarge(f"the request body exceeds {max_bytes} bytes")
        return body
    if encoding != "gzip":
        raise BodyUnreadable(f"Content-Encoding {encoding!r} is not accepted (send identity or gzip)")
    inflater = zlib.decompressobj(wbits=16 + zlib.MAX_WBITS)
    try:
        out = inflater.decompress(body, max_bytes + 1)
    except zlib.error as exc:
        raise BodyUnreadable(f"the gzip body does not inflate: {exc}") from None
    if len(out) > max_bytes or inflater.unconsumed_tail:
        raise BodyTooLarge(f"the request body exceeds {max_bytes} bytes once gzip is undone")
    if not inflater.eof:
        raise BodyUnreadable("the gzip body is truncated")
    return out


def bad_record_of(error: ValidationError, raw: bytes) -> dict[str, Any]:
    """``bad_record`` for a batch that does not parse: the first error's record, and what is wrong."""
    first = error.errors(include_url=False, include_input=False)[0]
    loc = list(first.get("loc", ()))
    message = str(first.get("msg", "invalid")).removeprefix("Value error, ")
    index = loc[1] if len(loc) >= 2 and loc[0] == "records" and isinstance(loc[1], int) else None
    where = ".".join(str(part) for part in loc[2:] if not (isinstance(part, str) and part in _KINDS))
    uid = kind = None
    if index is not None:
        record = _raw_record(raw, index)
        uid = record.get("uid") if isinstance(record.get("uid"), str) else None
        kind = record.get("kind") if isinstance(record.get("kind"), str) else None
    return {"index": index, "uid": uid, "kind": kind, "error": f"{where}: {message}" if where else message}


_KINDS = {"node", "measurement", "baseline", "detection", "state_change", "alert_event"}


def _raw_record(raw: bytes, index: int) -> dict[str, Any]:
    try:
        records = json.loads(raw).get("records")
        record = records[index]
    except (ValueError, AttributeError, IndexError, TypeError, KeyError):
        return {}
    return record if isinstance(record, dict) else {}


def parse_batch(raw: bytes) -> IngestBatch:
    """The batch, or :class:`ValidationError` (say which record with :func:`bad_record_of`)."""
    return IngestBatch.model_validate_json(raw)


def store(database: Database, batch: IngestBatch, *, key_site: str, alert_sinks: list[str]) -> IngestOutcome:
    """Store the batch in one transaction; a concurrent twin (another worker) makes the retry all duplicates."""
    for attempt in range(2):
        try:
            with database.write() as session:
                return ingest_batch(session, batch, key_site=key_site, alert_sinks=alert_sinks)
        except sa_exc.IntegrityError:
            # Another worker stored some of these uids between our check and our insert; once more,
            # it finds them held. A second collision is a real conflict.
            if attempt == 1:
                raise IngestRefused("invalid", "the batch conflicts with records stored meanwhile; retry it") from None
    raise AssertionError("unreachable")


def note_refusal(database: Database, kind: str | None, uid: str | None, refusal: str, *, key_site: str) -> bool:
    """The batch was refused because of the record ``uid`` (a ``kind``): if it is a measurement whose
    traces a request of ``key_site`` awaits (the gateway's re-send), that request ends ``refused``
    with ``refusal`` (``db.trace_requests.refuse_resent``); True if one did.

    Its own transaction, the batch's having rolled back. A StorageError propagates (the caller
    answers 503, so the gateway sends the batch again, not counting a refusal, and the refusal is
    noted then): a refusal is never answered without being noted.
    """
    if kind != "measurement" or uid is None:
        return False
    with database.write() as session:
        refused = refuse_resent(session, uid, refusal, site=key_site)
    if refused:
        log.warning("ingest: the record re-sent with the traces of %s was refused, so is its trace request: %s",
                    uid, refusal)
    return refused


class IngestGate:
    """At most ``limit`` batches being stored at once in this worker; one more is turned away at once (429).

    Entered and left on the event loop's thread only, so a plain counter is exact.
    """

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.active = 0

    def try_enter(self) -> bool:
        if self.active >= self.limit:
            return False
        self.active += 1
        return True

    def leave(self) -> None:
        self.active -= 1
