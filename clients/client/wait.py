"""The decisions of `wait_for_state`, shared by the blocking and async clients.

Only the sleeping differs between the two (time.sleep, asyncio.sleep): what
counts as arrived, as failed or as too late is decided here, once.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from typing import Any

from clients.client.config import normalize_state
from clients.client.errors import CellFaulted, WaitTimeout


class StateWait:
    """One wait: its target, its deadline, and the last GET /state it saw."""

    def __init__(self, target: str, timeout: float, fail_on: Iterable[str]) -> None:
        self.target = normalize_state(target)
        self.timeout = timeout
        self.deadline = time.monotonic() + timeout
        self.fail_on = {normalize_state(s) for s in fail_on} - {self.target}
        self.last: dict[str, Any] | None = None

    def reached(self, snapshot: dict[str, Any]) -> bool:
        """True at the target; raises CellFaulted in a fail state.

        A fail state counts whenever it is seen, even on the first poll: an
        operation can fail within milliseconds of being accepted, before any
        poll, and a script that started it must not wait for a reset instead.
        """
        self.last = snapshot
        state = snapshot.get("state")
        if state == self.target:
            return True
        if state in self.fail_on:
            fault = snapshot.get("error") or snapshot.get("stop_reason") or {}
            why = f": {fault['message']}" if fault.get("message") else ""
            raise CellFaulted(f"the cell is in {state}, waiting for {self.target}{why}", snapshot)
        return False

    def remaining(self) -> float:
        return self.deadline - time.monotonic()

    def expired(self) -> WaitTimeout:
        where = f"; the cell is in {self.last['state']}" if self.last else ""
        return WaitTimeout(
            f"timed out after {self.timeout:g} s waiting for {self.target}{where}", self.last
        )
