"""What the worker knows, gathered as the facts each decision reads (`machine/decide.py`).

The decision is pure, so everything it reads is gathered here first: which
devices are known disconnected or faulted (without asking them: a reset's probe
asks), and, for a start or a create-workpiece, what the library and the
calibrations say. Only these two events read the library, so only they pay for it.
"""

from __future__ import annotations

from typing import Protocol

from server.core.machine.decide import NO_LIBRARY, ActiveOrder, Library
from server.core.machine.events import CreateWorkpiecePayload, Payload, StartPayload
from server.core.machine.transitions import TRANSITIONS, Event, State
from server.core.operations.camera_frames import robot_calibration_problem
from server.core.worker.devices import CellDevices
from server.storage import CellStores

LIBRARY_EVENTS = frozenset({Event.START_REQUESTED, Event.CREATE_WORKPIECE_REQUESTED})


class Order(Protocol):
    """What a decision reads of a production order."""

    @property
    def order_id(self) -> str: ...
    @property
    def workpiece_id(self) -> str: ...


class OrderSource(Protocol):
    """Where the worker learns the production order the cell works through (the order book)."""

    @property
    def active(self) -> Order | None: ...


def active_order(orders: OrderSource | None) -> ActiveOrder | None:
    """A frozen copy of the order the cell works through (the book's order is its own)."""
    active = orders.active if orders is not None else None
    return ActiveOrder(active.order_id, active.workpiece_id) if active is not None else None


def library_for(
    event: Event, payload: Payload, state: State, order: ActiveOrder | None, stores: CellStores
) -> Library:
    """What the library says for `event`: read only for an event it concerns that the
    table accepts in `state` (the decision asks it only then); `NO_LIBRARY` otherwise."""
    if event in LIBRARY_EVENTS and event in TRANSITIONS[state]:
        return library_facts(event, payload, order, stores)
    return NO_LIBRARY


def known_device_faults(devices: CellDevices) -> tuple[str, ...]:
    """The faults the devices' health already reports, and which are not connected.

    Asked for every event decided and every snapshot, so the usual answer (all
    connected, no fault) is found without building anything."""
    robot, glue, camera = devices.robot.health, devices.glue.health, devices.camera.health
    if (
        robot.connected
        and glue.connected
        and camera.connected
        and not (robot.active_faults or glue.active_faults or camera.active_faults)
    ):
        return ()
    known: list[str] = []
    for name, health in (("robot", robot), ("glue", glue), ("camera", camera)):
        if not health.connected:
            known.append(f"{name}: not connected")
        elif health.active_faults:
            known.extend(health.active_faults)
    return tuple(known)


def library_facts(
    event: Event, payload: Payload, order: ActiveOrder | None, stores: CellStores
) -> Library:
    """What the library and the calibrations say about the parts `event` may name."""
    if event is Event.START_REQUESTED and isinstance(payload, StartPayload):
        named = {payload.workpiece_id, order.workpiece_id if order is not None else None}
        if not payload.contour_matching:
            return Library(_known(named, stores))
        problem = robot_calibration_problem(stores.calibration, "contour matching")
        return Library(
            known=_known(named, stores),
            empty=stores.workpieces.is_empty(),
            calibration_problem=str(problem) if problem is not None else None,
        )
    if event is Event.CREATE_WORKPIECE_REQUESTED and isinstance(payload, CreateWorkpiecePayload):
        problem = robot_calibration_problem(stores.calibration, "workpiece creation")
        return Library(
            known=_known({payload.workpiece_id}, stores),
            calibration_problem=str(problem) if problem is not None else None,
        )
    return NO_LIBRARY


def _known(names: set[str | None], stores: CellStores) -> frozenset[str]:
    library = stores.workpieces
    return frozenset(name for name in names if name and library.exists(name))
