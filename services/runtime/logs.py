"""Log set-up shared by every artrack process: one line per record, plain text or JSON.

The format comes from ``--log-format text|json`` or the environment variable
``ARTRACK_LOG_FORMAT`` (default ``text``); ``artrack up`` exports the variable so the node
processes it starts log the same way. A JSON line is one object with ``time`` (ISO 8601,
UTC, milliseconds), ``level``, ``logger``, ``node`` (null outside node processes),
``message``, ``exception`` when there is one, and every field passed to the logging call
with ``extra={...}``. Rotation is left to the host (journald, docker, logrotate): artrack
writes to stderr only and opens no log file.

``ARTRACK_LOG_LEVEL`` (default ``INFO``) sets the level of artrack's own loggers (``artrack``,
``services``, ``protocol`` and below); other libraries' records under WARNING are left out unless
the level is DEBUG, so that a library's start-up chatter (numexpr announcing its threads when
pandas is installed) never lands between artrack's lines, nor in a command's one-line error.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import threading
from datetime import UTC, datetime
from typing import Literal, cast

FORMAT_ENV = "ARTRACK_LOG_FORMAT"
LEVEL_ENV = "ARTRACK_LOG_LEVEL"
FORMATS = ("text", "json")
OWN_LOGGERS = ("artrack", "services", "protocol")

LogFormat = Literal["text", "json"]

_STANDARD = frozenset(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {"message", "asctime"}


class NodeTag(logging.Filter):
    """Tags each record with the node it comes from (``record.node``): ``node``, or in a process group the
    node whose thread logs it (threads named after one of ``members``)."""

    def __init__(self, node: str | None, members: frozenset[str] = frozenset()):
        super().__init__()
        self.node = node
        self.members = members

    def filter(self, record: logging.LogRecord) -> bool:
        thread = threading.current_thread().name
        record.node = thread if thread in self.members else self.node
        return True


class JsonFormatter(logging.Formatter):
    """One JSON object per record (see the module docstring)."""

    def format(self, record: logging.LogRecord) -> str:
        entry = {
            "time": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname.lower(),
            "logger": record.name,
            "node": getattr(record, "node", None),
            "message": record.getMessage(),
        }
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        entry.update({k: v for k, v in vars(record).items() if k not in _STANDARD and k not in entry})
        return json.dumps(entry, default=str)


class OthersBelowWarning(logging.Filter):
    """Lets through every record of artrack's own loggers and other loggers' from WARNING up."""

    def filter(self, record: logging.LogRecord) -> bool:
        own = record.name.split(".", 1)[0] in OWN_LOGGERS
        return own or record.levelno >= logging.WARNING


def log_format(given: str | None = None) -> LogFormat:
    """``given``, else ``$ARTRACK_LOG_FORMAT``, else ``text``; ValueError naming a bad value."""
    value = (given or os.environ.get(FORMAT_ENV) or "text").lower()
    if value not in FORMATS:
        raise ValueError(f"log format {value!r} ({FORMAT_ENV} or --log-format) is not one of {', '.join(FORMATS)}")
    return cast(LogFormat, value)


def setup_logging(*, log_format: LogFormat = "text", level: str | None = None, node: str | None = None,
                  members: frozenset[str] = frozenset()) -> None:
    """Send log records to stderr in ``log_format`` (``node`` tags every line; in a process group, a line
    logged on the thread of one of ``members`` is tagged with that node instead)."""
    level = level or os.environ.get(LEVEL_ENV, "INFO")
    handler = logging.StreamHandler(sys.stderr)
    handler.addFilter(NodeTag(node, members))
    if log_format == "json":
        handler.setFormatter(JsonFormatter())
    elif node or members:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s [%(node)s] %(name)s: %(message)s"))
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    if root.level > logging.DEBUG:
        handler.addFilter(OthersBelowWarning())


def native_logs_to_stderr() -> None:
    """Send what native libraries write to file descriptor 1 to stderr, keeping ``sys.stdout`` on
    the process's real standard output.

    Zenoh's own log lines (Rust, enabled by ``RUST_LOG``, and errors such as a gossip message
    about an unknown link) are written to descriptor 1, where they would land in a command's
    output (``status --json``, ``echo``, ``export``). After this call descriptor 1 is a copy of
    stderr (and so is every child process's standard output), while Python's ``print`` writes to
    a new descriptor on the original stdout. Does nothing when ``sys.stdout`` is not on
    descriptor 1 (already moved, or replaced by a caller such as a test's capture)."""
    try:
        on_fd1 = sys.stdout is not None and sys.stdout.fileno() == 1
    except (AttributeError, OSError, ValueError):
        on_fd1 = False
    if not on_fd1:
        return
    sys.stdout.flush()
    original = os.dup(1)
    os.dup2(2, 1)
    sys.stdout = os.fdopen(original, "w", buffering=1, encoding=sys.stdout.encoding, errors=sys.stdout.errors)
