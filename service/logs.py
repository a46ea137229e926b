"""Structured (JSON lines) logging for the service."""

from __future__ import annotations

import json
import logging
import sys
import time


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        d = {
            "ts": round(time.time(), 3),
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": record.getMessage(),
        }
        extra = getattr(record, "fields", None)
        if extra:
            d.update(extra)
        if record.exc_info:
            d["exc"] = self.formatException(record.exc_info)
        return json.dumps(d, default=str)


def setup(level: str = "info") -> logging.Logger:
    h = logging.StreamHandler(sys.stderr)
    h.setFormatter(JsonFormatter())
    log = logging.getLogger("vgq.service")
    log.handlers[:] = [h]
    log.setLevel(level.upper())
    log.propagate = False
    return log


def event(log: logging.Logger, msg: str, level: int = logging.INFO, **fields) -> None:
    if log.isEnabledFor(level):
        log.log(level, msg, extra={"fields": fields})
