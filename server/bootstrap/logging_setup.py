"""Logging as the specification writes it (section 8.3), to the console and a rotating file.

    2025-08-21 14:30:25.123 [ERROR] server.core.worker.state_changes: fault NO_ANSWER from robot in
        EXECUTING_TRAJECTORY state (3f2a1c-000042)          [one line in the file]
      Error: the robot controller at 10.0.0.5:30003 stopped answering (...)
      Context: {'operation': 'trajectory', 'run_id': '3f2a1c-000040', 'workpiece_id': ...}
      Trace:                                              [when an exception caused it]
        Traceback (most recent call last): ...

Every line logged while the worker handles an event, or by the operation that
event started, carries the event id, so a technician can go from a log line to
the journal's record of that event and back. Files rotate at log_rotation_size
and are deleted after log_retention_days.

No secret reaches a line (docs/security.md, "Logs"): every handler carries a
`RedactingFilter` that rewrites each record's final text, arguments and
exception included, through server/security/redaction.py, whichever library made
it. uvicorn's lines keep a request's path and drop its query (where `?token=` and
`?ticket=` ride), and httpx and httpcore log warnings only: their per-request lines
name a webhook's whole URL, whose path and query are its receiver's secret.
"""

from __future__ import annotations

import io
import logging
import logging.handlers
import os
import time
from pathlib import Path

from server.common.event_id import current_event_id
from server.common.values import byte_size
from server.security.redaction import Redactor, path_only
from server.settings.model import Settings
from server.storage.permissions import LOG_FILE_MODE, private_directory

FORMAT = "%(asctime)s.%(msecs)03d [%(levelname)s] %(name)s: %(message)s%(event_suffix)s"
DATE_FORMAT = "%Y-%m-%d %H:%M:%S"


class EventIdFilter(logging.Filter):
    """Adds ` (event <id>)` to records made while an event is being handled."""

    def filter(self, record: logging.LogRecord) -> bool:
        event_id = current_event_id.get()
        record.event_suffix = (
            f" (event {event_id})" if event_id and event_id not in record.getMessage() else ""
        )
        return True


# Libraries whose per-request INFO and DEBUG lines carry URLs, headers or payloads.
QUIETED_LOGGERS = ("httpx", "httpcore")


class RedactingFilter(logging.Filter):
    """Rewrites a record so that what any handler writes of it carries no secret.

    A filter on the handlers, not on the loggers: a handler's filters see every record
    that reaches it, also those of libraries' loggers that propagate to the root. The
    record's message is formatted here and redacted (its arguments are then dropped),
    and so are its exception text, stack and the `error` and `context` extras.
    """

    def __init__(self, redactor: Redactor) -> None:
        super().__init__()
        self.redact = redactor

    def filter(self, record: logging.LogRecord) -> bool:
        if getattr(record, "glue_redacted", False):
            return True  # the other handler's filter did it already
        if record.name.startswith("uvicorn.") and isinstance(record.args, tuple):
            # The access line and the WebSocket lines: the request target without its query.
            record.args = tuple(
                path_only(a) if isinstance(a, str) and a.startswith("/") else a for a in record.args
            )
        record.msg = self.redact(record.getMessage())
        record.args = None
        if record.exc_info and not record.exc_text:
            record.exc_text = _EXCEPTION_FORMATTER.formatException(record.exc_info)
        if record.exc_text:
            record.exc_text = self.redact(record.exc_text)
        if record.stack_info:
            record.stack_info = self.redact(record.stack_info)
        error = getattr(record, "error", None)
        if error is not None:
            record.error = self.redact(str(error))
        context = getattr(record, "context", None)
        if context:
            record.context = _Shown(self.redact(repr(context)))
        trace = getattr(record, "trace", None)
        if trace:
            record.trace = self.redact(str(trace))
        record.glue_redacted = True
        return True


class _Shown(str):
    """Text that a formatter's `!r` writes as it is (a redacted repr)."""

    def __repr__(self) -> str:
        return str(self)


_EXCEPTION_FORMATTER = logging.Formatter()


class SpecFormatter(logging.Formatter):
    """One timestamped line, then the specification's `Error:` and `Context:` lines.

    A record logged with `extra={"error": ..., "context": {...}, "trace": ...}` (the
    worker's fault records) gets them indented below it, so the first line stays
    the one to grep for and every following line is visibly part of it; `Trace:`
    follows, each line of the stack indented, when an exception caused the fault.
    """

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        error = getattr(record, "error", None)
        context = getattr(record, "context", None)
        trace = getattr(record, "trace", None)
        if error is not None:
            text += f"\n  Error: {error}"
        if context:
            text += f"\n  Context: {context!r}"
        if trace:
            text += "\n  Trace:\n" + "\n".join(f"    {line}" for line in str(trace).splitlines())
        return text


class RetainingFileHandler(logging.handlers.RotatingFileHandler):
    """Size-based rotation that also deletes rotated files older than the retention."""

    def __init__(self, path: Path, max_bytes: int, retention_days: int) -> None:
        private_directory(path.parent)
        super().__init__(path, maxBytes=max_bytes, backupCount=1000, encoding="utf-8")
        self.retention_s = retention_days * 86_400
        self.prune()

    def _open(self) -> io.TextIOWrapper:
        """The log file, 0640 whatever the umask (server/storage/permissions.py)."""
        stream = super()._open()
        os.fchmod(stream.fileno(), LOG_FILE_MODE)
        return stream

    def doRollover(self) -> None:
        super().doRollover()
        self.prune()

    def prune(self) -> None:
        base = Path(self.baseFilename)
        cutoff = time.time() - self.retention_s
        for rotated in base.parent.glob(base.name + ".*"):
            if rotated.stat().st_mtime < cutoff:
                rotated.unlink(missing_ok=True)


def log_path(settings: Settings) -> Path:
    """Where the log file is (log_file_path, by default under the data directory)."""
    return settings.log_file


def configure(settings: Settings) -> Path:
    """Console and file logging at the configured level, secrets redacted; the file's path."""
    path = log_path(settings)
    formatter = SpecFormatter(FORMAT, DATE_FORMAT)
    event_filter = EventIdFilter()
    redacting = RedactingFilter(Redactor(target.url for target in settings.webhooks))
    console = logging.StreamHandler()
    file = RetainingFileHandler(
        path, byte_size(settings.log_rotation_size), settings.log_retention_days
    )
    root = logging.getLogger()
    for handler in list(root.handlers):
        root.removeHandler(handler)
    for handler in (console, file):
        handler.setFormatter(formatter)
        handler.addFilter(event_filter)
        handler.addFilter(redacting)
        root.addHandler(handler)
    root.setLevel(settings.logging_level)
    for name in QUIETED_LOGGERS:
        logging.getLogger(name).setLevel(logging.WARNING)
    return path
