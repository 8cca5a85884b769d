"""Who hears of a worker's decision as it is made, before its actions run.

A transport that shows the cell as another state model (OPC UA's PackML, where
Stopping, Holding, Aborting and Clearing are states of their own) must know when
the cell begins to act on a command, not only when the new state is entered: the
halt, the hold and a reset's probe of the devices happen between the two. The
worker tells each listener of every verdict here, synchronously and before the
first action; a listener only notes it (it must neither block nor await), and an
exception in one is logged and ignored, so no listener can hold or break the
worker.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from server.core.machine.transitions import Event, State

log = logging.getLogger(__name__)

Verdict = Literal["accepted", "probing", "refused"]


@dataclass(frozen=True, slots=True)
class DecisionNote:
    """One verdict: in `state`, `event` was accepted (towards `target`), sent to probe
    the devices first (a reset), or refused."""

    state: State
    event: Event
    verdict: Verdict
    target: State | None
    at: float  # when it was decided (the worker's clock, Unix seconds)


DecisionListener = Callable[[DecisionNote], None]


class DecisionListeners:
    """The listeners of one worker."""

    def __init__(self) -> None:
        # Read by the worker for every event (a list's truth costs no call): add and
        # remove change it.
        self.listeners: list[DecisionListener] = []

    def add(self, listener: DecisionListener) -> None:
        self.listeners.append(listener)

    def remove(self, listener: DecisionListener) -> None:
        if listener in self.listeners:
            self.listeners.remove(listener)

    def __bool__(self) -> bool:
        """Whether anyone listens: the worker builds no note for nobody."""
        return bool(self.listeners)

    def tell(self, note: DecisionNote) -> None:
        """Give `note` to every listener; one that raises is logged and skipped."""
        for listener in tuple(self.listeners):
            try:
                listener(note)
            except Exception:
                log.exception("a decision listener failed on %s in %s", note.event, note.state)
