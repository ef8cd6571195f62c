"""A scripted stand-in for the central ingest endpoint: a real HTTP server on 127.0.0.1 (ephemeral port).

It answers its ``script`` for the first requests (a status, headers, a problem+json body), then
stores every valid batch it gets the way the contract says (by uid: a second sight is a
duplicate) and answers the ingest result. Every request is recorded, decoded. The sender's own
tests use it to provoke answers the real centre gives only under load or on bad input; the
end-to-end tests use the real central service (tests/uplink/).
"""
from __future__ import annotations

import gzip
import json
import threading
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler
from typing import Any

from tests.support.local_http import serve_locally, stop_serving, url_of
from uplink.contract import IngestBatch, IngestResult


@dataclass(frozen=True)
class Reply:
    status: int
    headers: dict[str, str] = field(default_factory=dict)
    body: dict[str, Any] | None = None


def bad_record(index: int, error: str = "bad value", status: int = 422) -> Reply:
    return Reply(status, {"Content-Type": "application/problem+json"},
                 {"type": "urn:pipesentry:problem:ingest-bad-record", "title": "refused", "status": status,
                  "detail": f"record {index}: {error}", "bad_record": {"index": index, "uid": None, "kind": None,
                                                                       "error": error}})


@dataclass(frozen=True)
class Seen:
    headers: dict[str, str]
    batch: IngestBatch
    status: int


class ScriptedCentre:
    def __init__(self, script: list[Reply] | None = None) -> None:
        self.script = list(script or [])
        self.seen: list[Seen] = []
        self.held: dict[str, Any] = {}  # uid -> record, as stored
        self._lock = threading.Lock()
        self.server = serve_locally(self._handler())

    @property
    def url(self) -> str:
        return url_of(self.server)

    def _handler(self):
        centre = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args) -> None:
                pass

            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("Content-Length", "0")))
                headers = {k.lower(): v for k, v in self.headers.items()}
                if headers.get("content-encoding") == "gzip":
                    body = gzip.decompress(body)
                batch = IngestBatch.model_validate_json(body)
                reply = centre._answer(batch)
                with centre._lock:
                    centre.seen.append(Seen(headers, batch, reply.status))
                payload = json.dumps(reply.body).encode()
                self.send_response(reply.status)
                for name, value in {"Content-Type": "application/json", **reply.headers}.items():
                    self.send_header(name, value)
                self.send_header("Content-Length", str(len(payload)))
                self.end_headers()
                self.wfile.write(payload)

        return Handler

    def _answer(self, batch: IngestBatch) -> Reply:
        with self._lock:
            if self.script:
                return self.script.pop(0)
            accepted = duplicates = 0
            for record in batch.records:
                if record.uid in self.held:
                    duplicates += 1
                else:
                    self.held[record.uid] = record
                    accepted += 1
        result = IngestResult(batch_id=batch.batch_id, accepted=accepted, duplicates=duplicates)
        return Reply(200, {}, result.model_dump(mode="json"))

    def close(self) -> None:
        stop_serving(self.server)
