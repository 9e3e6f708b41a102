"""Keep API keys out of the server logs: uvicorn logs WebSocket paths with their query
string, and the stream accepts ``?key=...``. The filter masks the value of any ``key``
query parameter and any ``mlk_...`` token in uvicorn's records."""

from __future__ import annotations

import logging
import re

_PATTERNS = (re.compile(r"((?:[?&]|\b)key=)[^&\s\"']+"), re.compile(r"\bmlk_[A-Za-z0-9_-]{4,}"))
LOGGERS = ("uvicorn.error", "uvicorn.access")


def redact(text: str) -> str:
    text = _PATTERNS[0].sub(r"\1***", text)
    return _PATTERNS[1].sub("mlk_***", text)


class RedactKeysFilter(logging.Filter):
    """Masks API keys in a record's message and string arguments."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = redact(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(redact(a) if isinstance(a, str) else a for a in record.args)
        elif isinstance(record.args, dict):
            record.args = {
                k: redact(v) if isinstance(v, str) else v for k, v in record.args.items()
            }
        return True


def install_log_redaction() -> None:
    """Add the filter to uvicorn's loggers (once; called by the lifespan)."""
    for name in LOGGERS:
        logger = logging.getLogger(name)
        if not any(isinstance(f, RedactKeysFilter) for f in logger.filters):
            logger.addFilter(RedactKeysFilter())
