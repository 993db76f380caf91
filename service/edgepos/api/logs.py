"""Structured logs: one JSON object per line on stderr, with the request id of the request being
served. Nothing logged may carry a secret: the service never passes headers, bodies or query
strings to a logger, and a filter scrubs anything shaped like a bearer credential, a session token
or the admin key as a second line of defence."""

from __future__ import annotations

import contextvars
import json
import logging
import re
import sys
from typing import Any

request_id_var: contextvars.ContextVar[str | None] = contextvars.ContextVar(
    "edgepos_request_id", default=None
)

_STANDARD_ATTRIBUTES = set(vars(logging.makeLogRecord({}))) | {
    "message",
    "asctime",
    "taskName",
    "color_message",
}
_SECRET_PATTERNS = [
    re.compile(r"(?i:bearer)\s+\S+"),  # the flag scoped, so that the pattern can join an alternation
    re.compile(r"\b[0-9a-f]{32}\.[A-Za-z0-9_-]{16,}"),  # session tokens: <session id>.<secret>
]
REDACTED = "[redacted]"
_ENCODER = json.JSONEncoder(default=str, separators=(",", ":"))
"""``json.dumps(entry, default=str, separators=(",", ":"))``, with the encoder made once instead of per line."""


class JsonFormatter(logging.Formatter):
    """``{"ts", "level", "logger", "message", "request_id"?, ...extra}`` on one line."""

    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, Any] = {
            "ts": round(record.created, 6),
            "level": record.levelname.lower(),
            "logger": record.name,
            "message": record.getMessage(),
        }
        request_id = request_id_var.get()
        if request_id is not None:
            entry["request_id"] = request_id
        for key, value in vars(record).items():
            if key not in _STANDARD_ATTRIBUTES and not key.startswith("_"):
                entry[key] = value
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        return _ENCODER.encode(entry)


class RedactSecrets(logging.Filter):
    """Replace the admin key and anything credential-shaped in a record's text with [redacted]."""

    def __init__(self, secrets: list[str] | None = None) -> None:
        super().__init__()
        self.secrets = [s for s in (secrets or []) if s]
        # Any secret or pattern anywhere in a text, in one search: most texts (an access line's method,
        # route and path) hold none and are kept as they are without the replacements' passes.
        self._anything = re.compile(
            "|".join([*(re.escape(s) for s in self.secrets), *(p.pattern for p in _SECRET_PATTERNS)])
        )

    def scrub(self, text: str) -> str:
        if self._anything.search(text) is None:
            return text
        for secret in self.secrets:
            text = text.replace(secret, REDACTED)
        for pattern in _SECRET_PATTERNS:
            text = pattern.sub(REDACTED, text)
        return text

    def filter(self, record: logging.LogRecord) -> bool:
        record.msg = self.scrub(record.getMessage())
        record.args = None
        attributes = vars(record)
        for key in attributes.keys() - _STANDARD_ATTRIBUTES:  # the extras, found in one set operation
            value = attributes[key]
            if isinstance(value, str):
                setattr(record, key, self.scrub(value))
        return True


_HANDLER_NAME = "edgepos-json"


def configure_logging(level: str, secrets: list[str] | None = None) -> None:
    """Send the ``edgepos`` and ``uvicorn`` loggers to stderr as JSON lines (idempotent: a second
    call replaces the handler of the first)."""
    numeric = getattr(logging, level.upper(), logging.INFO)
    for name in ("edgepos", "uvicorn"):
        logger = logging.getLogger(name)
        for old in [h for h in logger.handlers if h.get_name() == _HANDLER_NAME]:
            logger.removeHandler(old)
        handler = logging.StreamHandler(sys.stderr)
        handler.set_name(_HANDLER_NAME)
        handler.setFormatter(JsonFormatter())
        handler.addFilter(RedactSecrets(secrets))
        logger.addHandler(handler)
        logger.setLevel(numeric)
        logger.propagate = False
    logging.getLogger("uvicorn.access").disabled = True  # the service's own access log replaces it
