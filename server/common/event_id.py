"""The id of the event the worker is handling, for whatever is logged or warned meanwhile.

The worker sets it around each event it handles; the log filter
(`server/bootstrap/logging_setup.py`) appends it to every line written in that time,
and a warning journaled meanwhile carries it. A context variable, so an operation's
task started while an event was handled keeps that event's id.
"""

from __future__ import annotations

import contextvars

current_event_id: contextvars.ContextVar[str | None] = contextvars.ContextVar(
    "current_event_id", default=None
)
