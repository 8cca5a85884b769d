"""Warnings: conditions a technician should hear of while the cell runs on.

Why: a cell whose operations creep towards processing_timeout, whose
calibration error creeps towards its limit, or that sits in ERROR unattended
is about to cost production; each is logged, journaled as a warning (not
counted in the KPI error rate) and pushed on /ws as an `alert`.

A warning whose cause the cell sees go away (a maintenance item done, a refill, the
memory back under its limit) is said to be over with `cleared`: an `alert_cleared`
bus message naming its code, so what keeps warnings as state (OPC UA's alarm
conditions, PackML's Admin.Warning) lets it go. Such a warning is raised `standing`:
it is kept in `standing` until cleared, so a subscriber that starts after it was raised
(the OPC UA alarms start after the cell, whose first care check may already have found
an item due) raises it from there.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from typing import Any

from server.common.event_id import current_event_id
from server.core.infra.bus import Bus
from server.core.infra.clock import Clock, Timer
from server.core.machine.transitions import State
from server.core.operations.base import OperationWarning
from server.core.worker.context import MachineContext
from server.core.worker.recorder import Recorder
from server.settings.model import Settings

log = logging.getLogger(__name__)

SLOW_OPERATION_SHARE = 0.8  # of processing_timeout: a run this slow is warned of


class Alerts:
    """Raises warnings, and the alert for a cell left in ERROR too long."""

    def __init__(
        self,
        settings: Settings,
        ctx: MachineContext,
        bus: Bus,
        recorder: Recorder,
        clock: Clock,
    ) -> None:
        self.settings = settings
        self.ctx = ctx
        self.bus = bus
        self.recorder = recorder
        self.clock = clock
        self._error_timer: Timer | None = None
        # The standing warnings raised and not cleared yet, by code: their bus message's
        # data, with the time each was raised.
        self.standing: dict[str, dict[str, Any]] = {}

    def warn(
        self,
        code: str,
        message: str,
        component: str,
        *,
        severity: str = "warning",
        standing: bool = False,
    ) -> None:
        """A warning-class condition: logged, journaled, pushed on /ws; the cell runs on.

        `severity` is "warning", or "alert" for one that needs someone now (the memory
        limit reached, the error rate risen, the configuration changed): the same
        channels, said in the message's `severity` and at the log's ERROR level. Either
        is journaled as a warning: neither is a fault, nor counts in the KPIs' error rate.
        `standing`: the warning holds until `cleared` says otherwise (kept in `standing`).
        """
        level = logging.ERROR if severity == "alert" else logging.WARNING
        log.log(level, "%s %s from %s: %s", severity, code, component, message)
        state = self.ctx.state.value
        data = {
            "code": code,
            "message": message,
            "component": component,
            "classification": "warning",
            "severity": severity,
            "state": state,
        }
        self.bus.publish("alert", data)
        if standing:
            self.standing[code] = {**data, "time": self.clock.time()}
        self.recorder.warning(code, message, component, current_event_id.get() or "", state)

    def cleared(self, code: str, message: str, component: str) -> None:
        """A warning's cause has gone: logged, and pushed as `alert_cleared` naming the code.

        Not journaled: the warning's row stays the record of what happened; what ended
        it (a maintenance item done, a refill) has its own audit row.
        """
        log.info("warning %s from %s cleared: %s", code, component, message)
        self.standing.pop(code, None)
        self.bus.publish(
            "alert_cleared",
            {
                "code": code,
                "message": message,
                "component": component,
                "state": self.ctx.state.value,
            },
        )

    def halt_incomplete(self, errors: Iterable[str]) -> None:
        """A safe halt a device did not confirm: pushed on /ws (the halt logged it)."""
        for error in errors:
            component = error.split(":", 1)[0]
            self.bus.publish(
                "error", {"code": "HALT_INCOMPLETE", "message": error, "component": component}
            )

    def of_completed_run(
        self, operation: str, seconds: float, warnings: Iterable[OperationWarning]
    ) -> None:
        """Warnings of a run that succeeded: it came close to its budget, or it said so."""
        budget = self.settings.processing_timeout
        if seconds > SLOW_OPERATION_SHARE * budget:
            self.warn(
                "SLOW_OPERATION",
                f"{operation} took {seconds:.1f} s of its {budget:g} s budget "
                "(processing_timeout): check device speeds and lighting before runs time out",
                operation,
            )
        for warning in warnings:
            self.warn(warning.code, warning.message, operation)

    def watch_state(self, state: State) -> None:
        """Start the ERROR-timeout alert on entering ERROR; stop it on leaving.

        A timer, not a task that sleeps: every entry into ERROR would otherwise
        cost the worker a task created and cancelled.
        """
        self.stop()
        if state is State.ERROR:
            self._error_timer = self.clock.call_later(
                self.settings.error_state_timeout, self._alert_after_timeout
            )

    def stop(self) -> None:
        if self._error_timer is not None:
            self._error_timer.cancel()
            self._error_timer = None

    def _alert_after_timeout(self) -> None:
        self._error_timer = None
        timeout = self.settings.error_state_timeout
        reason = self.ctx.stop_reason.message if self.ctx.stop_reason else "unknown"
        message = f"the cell has been in ERROR for {timeout:g} s (first fault: {reason})"
        self.warn("ERROR_STATE_TIMEOUT", message, "system")
