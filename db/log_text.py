"""Text bound for a log line or a stored error: no forged lines, no terminal escapes, no secrets.

Every process logs (the gateway, alert delivery, the API), and ``db`` is the layer they all
stand on, so the one formatter they share lives here.

* Operator-supplied strings (a baseline's or decommissioning's reason, a key's name) reach log
  messages verbatim: a newline in one would start a line that looks like the gateway's own, and
  an ANSI escape would reach the terminal of whoever reads the log. :func:`escape_controls`
  writes every control character as its Python escape (``\\n``, ``\\x1b``).
* URLs may carry credentials (``https://user:pass@host``, ``?token=...``): :func:`redact`
  replaces the user information and the query of every URL in a text, and every secret a
  sink registered with :func:`mask_secret` (a Slack webhook's URL is itself the credential).
"""
from __future__ import annotations

import logging
import re
import threading

MASK = "***"
_MIN_SECRET_CHARS = 6  # shorter "secrets" would mask ordinary words
# C0 controls but tab, DEL, C1 controls, and the two Unicode line separators.
_CONTROL = re.compile("[\x00-\x08\x0a-\x1f\x7f-\x9f\u2028\u2029]")
_USERINFO = re.compile(r"(?P<scheme>\b[A-Za-z][A-Za-z0-9+.-]*://)[^/@\s?#]+@")
_QUERY = re.compile(r"(?P<url>\b[A-Za-z][A-Za-z0-9+.-]*://[^\s?#]+)\?[^\s#\"']+")

_secrets: set[str] = set()
_lock = threading.Lock()


def escape_controls(text: str) -> str:
    """``text`` on one line: each control character as its escape (``\\n``, ``\\x1b``, ``\\u2028``)."""
    return _CONTROL.sub(lambda m: m.group().encode("unicode_escape").decode("ascii"), text)


def mask_secret(*secrets: str | None) -> None:
    """From now on, these strings are written as ``***`` wherever :func:`redact` runs."""
    with _lock:
        _secrets.update(s for s in secrets if s and len(s) >= _MIN_SECRET_CHARS)


def redact(text: str) -> str:
    """``text`` with registered secrets, URL user information and URL queries replaced by ``***``."""
    with _lock:
        secrets = sorted(_secrets, key=len, reverse=True)
    for secret in secrets:
        if secret in text:
            text = text.replace(secret, MASK)
    text = _USERINFO.sub(lambda m: f"{m.group('scheme')}{MASK}@", text)
    return _QUERY.sub(lambda m: f"{m.group('url')}?{MASK}", text)


def safe_text(text: str) -> str:
    """What a log line may show of ``text``: redacted, on one line."""
    return escape_controls(redact(text))


class SafeFormatter(logging.Formatter):
    """A ``logging.Formatter`` whose message is :func:`safe_text` and whose traceback is redacted.

    A traceback keeps its lines (it is the formatter's own text, not a forged one).
    """

    def formatMessage(self, record: logging.LogRecord) -> str:
        record.message = safe_text(record.message)
        return super().formatMessage(record)

    def formatException(self, ei) -> str:
        return redact(super().formatException(ei))


# Loggers of libraries that write request URLs at INFO (httpx: "HTTP Request: POST <url>"): a
# Slack webhook's URL is its credential. Warnings and errors still show (redacted).
CHATTY_URL_LOGGERS = ("httpx", "httpcore")


def quiet_url_loggers() -> None:
    for name in CHATTY_URL_LOGGERS:
        logging.getLogger(name).setLevel(logging.WARNING)
