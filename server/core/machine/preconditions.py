"""What a command needs besides the right state, checked before it is accepted.

Why: a run that cannot succeed (no workpiece named, an unknown part, no
calibration), once accepted, would fail inside the operation, driving the cell
into ERROR and needing a maintenance reset for an operator's typo.
What can be checked before the transition is checked before it: the command
is refused, the state does not change, and the refusal is journaled and
audited like any other. The operations check again when they run (the library
or the calibration may change in between), so this is the first line, not
the only one.

A `Refusal` with a `field` is the request's fault (HTTP 422 naming the field);
without one it is the cell's precondition (HTTP 409 saying what to do first).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from server.core.machine.events import CreateWorkpiecePayload, JogPayload, Payload, StartPayload
from server.core.machine.transitions import Event
from server.core.operations.camera_frames import robot_calibration_problem
from server.core.operations.jog import step_problem
from server.core.operations.safe_position import workspace_problem
from server.drivers.base import Pose
from server.settings.model import Settings
from server.storage import CellStores


@dataclass(frozen=True, slots=True)
class Refusal:
    """Why a command is refused before its transition; `field` names a wrong request field."""

    message: str
    field: str | None = None


class ActiveOrder(Protocol):
    """What a start needs to know of the production order the cell works through."""

    order_id: str
    workpiece_id: str


class Preconditions:
    """The checks of each command against the library, the calibrations and the orders."""

    def __init__(self, stores: CellStores, settings: Settings) -> None:
        self.stores = stores
        self.settings = settings
        # The order the cell works through, if any (the cell's order book sets it).
        self.active_order: Callable[[], ActiveOrder | None] = lambda: None

    def check(self, event: Event, payload: Payload) -> Refusal | None:
        """Why `event` with `payload` cannot be accepted now, or None when it can."""
        if isinstance(payload, StartPayload):
            return self._start(payload)
        if isinstance(payload, CreateWorkpiecePayload):
            return self._create_workpiece(payload)
        if isinstance(payload, JogPayload):
            wrong = step_problem(payload.axis, payload.distance_mm, self.settings)
            return Refusal(wrong[1], field=wrong[0]) if wrong is not None else None
        if event is Event.HOME_REQUESTED:  # checked at load too; again before anything moves
            problem = workspace_problem(
                Pose.from_sequence(self.settings.safe_position), self.settings
            )
            if problem is not None:
                return Refusal(
                    f"the safe position is outside the workspace ({problem}): correct "
                    "safe_position or the workspace bounds in the settings"
                )
        return None

    def _start(self, start: StartPayload) -> Refusal | None:
        order = self.active_order()
        if order is not None and start.workpiece_id not in (None, order.workpiece_id):
            # A person's start of the order's own part (or of none named) is one of its
            # parts (OrderBook.claim_start); a start of another workpiece is not now.
            return Refusal(
                f"order {order.order_id} is active and makes {order.workpiece_id!r}: close "
                "it first to spray another workpiece (this start: workpiece_id "
                f"{start.workpiece_id!r})"
            )
        library = self.stores.workpieces
        if not start.contour_matching and not start.workpiece_id:
            return Refusal(
                "workpiece_id is required when contour_matching is false: name the library "
                "part to spray (GET /workpieces lists them)",
                field="workpiece_id",
            )
        if start.workpiece_id and not library.exists(start.workpiece_id):
            return Refusal(
                f"workpiece {start.workpiece_id!r} is not in the library: GET /workpieces "
                "lists the parts, create-workpiece adds one"
            )
        if start.contour_matching:
            if library.is_empty():
                return Refusal(
                    "the workpiece library is empty: run create-workpiece with a part on the "
                    "table first"
                )
            problem = robot_calibration_problem(self.stores.calibration, "contour matching")
            if problem is not None:
                return Refusal(str(problem))
        return None

    def _create_workpiece(self, create: CreateWorkpiecePayload) -> Refusal | None:
        if create.workpiece_id and self.stores.workpieces.exists(create.workpiece_id):
            return Refusal(
                f"workpiece {create.workpiece_id!r} already exists and create-workpiece never "
                f"replaces a part: change it with PUT /workpieces/{create.workpiece_id} "
                "(maintenance), or choose another workpiece_id"
            )
        problem = robot_calibration_problem(self.stores.calibration, "workpiece creation")
        return Refusal(str(problem)) if problem is not None else None
