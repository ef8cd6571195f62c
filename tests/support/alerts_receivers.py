"""Real alert receivers for the alerting tests: threaded HTTP servers on 127.0.0.1 ephemeral ports.

A receiver follows a script of answers (``fail``, ``hang``, ``gone``) for its first
requests and answers 200 after that; it records every request it saw. Waiting for a
request is waiting on a condition variable, bounded in time. The Alertmanager stand-in
checks each POST against Alertmanager's v2 ``postableAlerts`` schema and answers 400
(recording why) when it does not match.
"""
from __future__ import annotations

import json
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime
from http.server import BaseHTTPRequestHandler
from typing import Any

from tests.support.local_http import serve_locally, stop_serving, url_of

HANG_LIMIT_S = 30.0  # a hanging answer never outlives the test


@dataclass(frozen=True)
class Answer:
    status: int = 200
    headers: dict[str, str] = field(default_factory=dict)
    hang: bool = False  # hold the request until released (the client times out)


OK = Answer()


def fail(status: int = 503, **headers: str) -> Answer:
    return Answer(status=status, headers=headers)


HANG = Answer(hang=True)
GONE = Answer(status=410)


@dataclass(frozen=True)
class Request:
    path: str
    headers: dict[str, str]
    body: bytes
    status: int  # what the receiver answered (0 when it hung up without answering)

    def json(self) -> Any:
        return json.loads(self.body)


class HttpReceiver:
    """A real HTTP server; ``script`` answers the first requests, then 200 for the rest."""

    def __init__(self, script: list[Answer] | None = None, validate: Callable[[str, bytes], str | None] | None = None):
        self.script = list(script or [])
        self.validate = validate
        self.requests: list[Request] = []
        self.invalid: list[str] = []
        self._cond = threading.Condition()
        self._release = threading.Event()
        self.server = serve_locally(self._handler_class())

    @property
    def url(self) -> str:
        return url_of(self.server)

    def _handler_class(self):
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args) -> None:
                pass

            def do_POST(self) -> None:
                length = int(self.headers.get("Content-Length", "0"))
                body = self.rfile.read(length)
                headers = {k.lower(): v for k, v in self.headers.items()}
                answer = receiver._next_answer()
                problem = receiver.validate(self.path, body) if receiver.validate else None
                if problem is not None:
                    answer = Answer(status=400)
                    with receiver._cond:
                        receiver.invalid.append(problem)
                if answer.hang:
                    receiver._record(Request(self.path, headers, body, 0))
                    receiver._release.wait(HANG_LIMIT_S)
                    self.close_connection = True
                    return
                # Recorded before answering: once the client has its answer, the test sees the request.
                receiver._record(Request(self.path, headers, body, answer.status))
                self.send_response(answer.status)
                for name, value in answer.headers.items():
                    self.send_header(name, value)
                self.send_header("Content-Length", "2")
                self.end_headers()
                self.wfile.write(b"ok")

        return Handler

    def _next_answer(self) -> Answer:
        with self._cond:
            return self.script.pop(0) if self.script else OK

    def _record(self, request: Request) -> None:
        with self._cond:
            self.requests.append(request)
            self._cond.notify_all()

    def wait_for(self, predicate: Callable[[list[Request]], bool], timeout_s: float, what: str) -> list[Request]:
        """Block until ``predicate(requests)`` holds; AssertionError after ``timeout_s``."""
        with self._cond:
            if not self._cond.wait_for(lambda: predicate(self.requests), timeout_s):
                raise AssertionError(f"timed out after {timeout_s} s waiting for {what}; got {len(self.requests)} requests")
            return list(self.requests)

    def accepted(self) -> list[Request]:
        with self._cond:
            return [r for r in self.requests if 200 <= r.status < 300]

    def close(self) -> None:
        self._release.set()
        stop_serving(self.server)


# ------------------------------------------------------------------ Alertmanager v2 schema
_POSTABLE_ALERT_KEYS = {"labels", "annotations", "startsAt", "endsAt", "generatorURL"}


def _rfc3339(value: Any) -> bool:
    if not isinstance(value, str) or "T" not in value:
        return False
    try:
        parsed = datetime.fromisoformat(value)
    except ValueError:
        return False
    return parsed.tzinfo is not None


def _string_map(value: Any) -> bool:
    return isinstance(value, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in value.items())


def postable_alerts_problem(path: str, body: bytes) -> str | None:
    """Why ``body`` is not a valid ``POST /api/v2/alerts`` (postableAlerts), or None if it is."""
    if path != "/api/v2/alerts":
        return f"wrong path {path}"
    try:
        alerts = json.loads(body)
    except ValueError as exc:
        return f"not JSON: {exc}"
    if not isinstance(alerts, list):
        return "postableAlerts must be an array"
    for i, alert in enumerate(alerts):
        if not isinstance(alert, dict):
            return f"[{i}] is not an object"
        extra = set(alert) - _POSTABLE_ALERT_KEYS
        if extra:
            return f"[{i}] unknown fields {sorted(extra)}"
        if "labels" not in alert or not _string_map(alert["labels"]) or not alert["labels"]:
            return f"[{i}].labels must be a non-empty map of strings"
        if "annotations" in alert and not _string_map(alert["annotations"]):
            return f"[{i}].annotations must be a map of strings"
        for key in ("startsAt", "endsAt"):
            if key in alert and not _rfc3339(alert[key]):
                return f"[{i}].{key} is not an RFC3339 date-time: {alert[key]!r}"
        if "startsAt" in alert and "endsAt" in alert:
            starts = datetime.fromisoformat(alert["startsAt"])
            ends = datetime.fromisoformat(alert["endsAt"])
            if ends < starts:
                return f"[{i}] endsAt is before startsAt"
        if "generatorURL" in alert and not (
            isinstance(alert["generatorURL"], str) and alert["generatorURL"].startswith(("http://", "https://"))
        ):
            return f"[{i}].generatorURL must be a URI"
    return None


def alertmanager_receiver(script: list[Answer] | None = None) -> HttpReceiver:
    return HttpReceiver(script, validate=postable_alerts_problem)
