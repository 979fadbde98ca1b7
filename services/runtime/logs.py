"""Log set-up shared by every artrack process: one line per record, plain or JSON.

JSON lines (``--log-json`` or ``ARTRACK_LOG_JSON=1``) carry ``ts`` (ISO 8601, UTC), ``level``,
``logger``, ``msg`` and, for node processes, ``node``. Rotation is left to the host
(journald, docker, logrotate): artrack writes to stderr only.
"""

from __future__ import annotations

import json
import logging
import os
import sys
from datetime import UTC, datetime


class _JsonFormatter(logging.Formatter):
    def __init__(self, node: str | None):
        super().__init__()
        self.node = node

    def format(self, record: logging.LogRecord) -> str:
        entry = {
            "ts": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": record.getMessage(),
        }
        if self.node:
            entry["node"] = self.node
        if record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        return json.dumps(entry)


def setup_logging(*, json_lines: bool | None = None, level: str | None = None, node: str | None = None) -> None:
    """Send log records to stderr, as JSON lines or plain text (``node`` tags every line)."""
    if json_lines is None:
        json_lines = os.environ.get("ARTRACK_LOG_JSON", "") not in ("", "0", "false")
    level = level or os.environ.get("ARTRACK_LOG_LEVEL", "INFO")
    handler = logging.StreamHandler(sys.stderr)
    if json_lines:
        handler.setFormatter(_JsonFormatter(node))
    else:
        tag = f"[{node}] " if node else ""
        handler.setFormatter(logging.Formatter(f"%(asctime)s %(levelname)s {tag}%(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
