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
import re
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
        own = record.name.split(".", 1)[0] in OWN_LOGGERS or record.name == NATIVE_LOGGER
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


NATIVE_LOGGER = "zenoh"
"""Logger of the lines native code writes to descriptor 1 (Zenoh's, in Rust) when logging JSON."""

_COLOUR = re.compile(r"\x1b\[[0-9;]*m")
_TRACING_LINE = re.compile(r"^\S+\s+(TRACE|DEBUG|INFO|WARN|ERROR)\s+(.*)$")
_GLOG_SIGNAL_REPORT = re.compile(r"\*\*\* (Aborted at|SIG[A-Z]+ \(@)|PC: @ |\s+@\s+0x[0-9a-f]+ ")
"""The lines of glog's report of a fatal signal: ``*** Aborted at ...``, ``*** SIGTERM (@0x...) received by PID
...``, ``PC: @ ...`` and one ``    @     0x... function`` per stack frame."""
_TRACING_LEVELS = {"TRACE": logging.DEBUG, "DEBUG": logging.DEBUG, "INFO": logging.INFO,
                   "WARN": logging.WARNING, "ERROR": logging.ERROR}


def native_record(line: str) -> tuple[int, str]:
    """The level and message of one line written by native code: a Rust ``tracing`` line
    (``<time> <LEVEL> <message>``, with or without terminal colours) keeps its level and loses its
    time and colours; any other line is a warning as it stands."""
    plain = _COLOUR.sub("", line).strip()
    match = _TRACING_LINE.match(plain)
    if match:
        return _TRACING_LEVELS[match[1]], match[2]
    return logging.WARNING, plain


def is_native_line(line: str) -> bool:
    """Whether a line a process wrote to stderr is native code's rather than its own: a Rust
    ``tracing`` line in colour, a JSON record of :data:`NATIVE_LOGGER`, or a line of the report glog's
    signal handler (installed by pycolmap) prints when a fatal signal reaches the process."""
    if line.startswith("\x1b[") or _GLOG_SIGNAL_REPORT.match(line):
        return True
    if not line.startswith("{"):
        return False
    try:
        return json.loads(line).get("logger") == NATIVE_LOGGER
    except (ValueError, AttributeError):
        return False


def _log_native_lines(fd: int) -> None:
    logger = logging.getLogger(NATIVE_LOGGER)
    with os.fdopen(fd, "rb") as pipe:
        for raw in pipe:
            level, message = native_record(raw.decode(errors="replace"))
            if message:
                logger.log(level, message)


def native_logs_to_stderr(log_format: LogFormat = "text") -> None:
    """Send what native libraries write to file descriptor 1 to stderr, keeping ``sys.stdout`` on
    the process's real standard output.

    Zenoh's own log lines (Rust, enabled by ``RUST_LOG``, and errors such as a gossip message
    about an unknown link) are written to descriptor 1, where they would land in a command's
    output (``status --json``, ``echo``, ``export``). After this call descriptor 1 leads to stderr
    (and so does every child process's standard output), while Python's ``print`` writes to a new
    descriptor on the original stdout. In ``text`` format descriptor 1 becomes a copy of stderr; in
    ``json`` format it becomes a pipe whose lines a thread logs as records of :data:`NATIVE_LOGGER`
    (level from the line, every level let through, ``RUST_LOG`` choosing how many), so that stderr
    holds JSON objects only. Does nothing when ``sys.stdout`` is not on descriptor 1 (already moved,
    or replaced by a caller such as a test's capture)."""
    try:
        on_fd1 = sys.stdout is not None and sys.stdout.fileno() == 1
    except (AttributeError, OSError, ValueError):
        on_fd1 = False
    if not on_fd1:
        return
    sys.stdout.flush()
    original = os.dup(1)
    if log_format == "json":
        read, write = os.pipe()
        os.dup2(write, 1)
        os.close(write)
        logging.getLogger(NATIVE_LOGGER).setLevel(logging.DEBUG)
        threading.Thread(target=_log_native_lines, args=(read,), name="native log lines", daemon=True).start()
    else:
        os.dup2(2, 1)
    sys.stdout = os.fdopen(original, "w", buffering=1, encoding=sys.stdout.encoding, errors=sys.stdout.errors)
