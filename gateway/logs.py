"""Structured logs: every line carries the node id (or ``-`` for the daemon itself); JSON optional.

Every line is one line and shows no secret: db/log_text.py escapes control characters in
messages and masks credentials (httpx's per-request INFO line, which names the URL, is off)."""
from __future__ import annotations

import contextvars
import json
import logging
import sys
from contextlib import contextmanager
from datetime import UTC, datetime

from db.log_text import SafeFormatter, quiet_url_loggers, redact, safe_text

current_node: contextvars.ContextVar[str] = contextvars.ContextVar("current_node", default="-")


class _NodeFilter(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        if not hasattr(record, "node"):
            record.node = current_node.get()
        return True


class JsonFormatter(logging.Formatter):
    """One JSON object per line: ts, level, logger, node, msg, and any ``extra=`` fields.

    Texts are redacted and on one line (db/log_text.py), as in the plain format."""

    _STANDARD = set(logging.LogRecord("", 0, "", 0, "", (), None).__dict__) | {"message", "node", "asctime"}

    def format(self, record: logging.LogRecord) -> str:
        doc = {
            "ts": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname,
            "logger": record.name,
            "node": getattr(record, "node", "-"),
            "msg": safe_text(record.getMessage()),
        }
        for key, value in record.__dict__.items():
            if key not in self._STANDARD and not key.startswith("_"):
                text = value if isinstance(value, (int, float, bool, type(None))) else safe_text(str(value))
                doc[key] = text
        if record.exc_info:
            doc["exc"] = redact(self.formatException(record.exc_info))
        return json.dumps(doc)


def setup_logging(level: str = "INFO", json_lines: bool = False, stream=None) -> None:
    """Configure the root logger once for the daemon."""
    handler = logging.StreamHandler(stream or sys.stderr)
    handler.addFilter(_NodeFilter())
    if json_lines:
        handler.setFormatter(JsonFormatter())
    else:
        handler.setFormatter(SafeFormatter("%(asctime)s %(levelname)s node=%(node)s %(name)s: %(message)s"))
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level)
    quiet_url_loggers()


@contextmanager
def node_context(node_id: str):
    """Tag every log line emitted inside the block (in this thread) with ``node_id``."""
    token = current_node.set(node_id)
    try:
        yield
    finally:
        current_node.reset(token)
