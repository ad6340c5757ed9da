"""Logging of a stage process: records carrying ``run`` and ``stage``, plain text or JSON lines."""

from __future__ import annotations

import json
import logging
import sys


class StageLogger(logging.LoggerAdapter):
    """Attaches ``run`` and ``stage`` (and any ``extra``) to the records of a stage."""

    def process(self, msg, kwargs):
        kwargs["extra"] = {**(self.extra or {}), **kwargs.get("extra", {})}
        return msg, kwargs


class JsonFormatter(logging.Formatter):
    """One JSON object per line: time, level, logger, message, and run/stage/index if set."""

    def format(self, record: logging.LogRecord) -> str:
        out = {
            "time": round(record.created, 6),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        for name in ("run", "stage", "index"):
            if hasattr(record, name):
                out[name] = getattr(record, name)
        if record.exc_info:
            out["exception"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str)


def configure_logging(level: str | int = "INFO", json_lines: bool = False, stream=None) -> None:
    """Set up the root logger of a stage process (plain text or JSON lines on stderr)."""
    handler = logging.StreamHandler(stream or sys.stderr)
    handler.setFormatter(
        JsonFormatter() if json_lines else logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
    )
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
