"""The specification's in-process API, for integrators who embed the cell.

`EmbeddedCell` offers the method names and return shapes of the original
application (`start(contourMatching=True) -> (bool, str)`, `calibrateRobot()
-> (bool, str, image)`, ...) over the very same Cell the HTTP API drives:
every call goes through `Cell.command`, the worker and the transition table.

The cell runs on its own event loop in a background thread, so the façade can
be called from ordinary synchronous code. Operations are replaceable: pass
`operations={"calibrate_robot": blocking_operation(app.calibrateRobot)}` to let
an existing application's method do the work while the state machine governs
when it may run.

    with EmbeddedCell() as cell:
        ok, message = cell.start(contourMatching=False)
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

import cv2
import numpy as np

from server.bootstrap.cell import Cell
from server.bootstrap.plant import stop_cell, webhooks_of
from server.core.machine.events import Payload, StartPayload, StopPayload
from server.core.machine.transitions import Command, State, normalize_command
from server.core.operations import Operation, OperationContext, OperationResult
from server.core.worker.devices import CellDevices
from server.core.worker.supervision import as_result
from server.settings.model import Settings

T = TypeVar("T")


def blocking_operation(function: Callable[[], Any]) -> Operation:
    """Wrap a synchronous callable (e.g. a legacy application method) as an operation.

    It runs in a worker thread; its return value becomes the result (a dict is
    kept as is, anything else is stored under "value"); an exception fails the
    operation. A thread cannot be cancelled: on cancel, e-stop or a fault the
    cell halts the devices and moves on, but the function runs to its end, so
    it must not command the devices itself after they were halted.
    """

    async def operation(ctx: OperationContext) -> OperationResult:
        return as_result(await asyncio.to_thread(function))

    return operation


class EmbeddedCell:
    """The cell as a synchronous Python object with the specification's methods."""

    def __init__(
        self,
        settings: Settings | None = None,
        *,
        devices: CellDevices | None = None,
        operations: dict[str, Operation] | None = None,
    ) -> None:
        self.cell = Cell(settings or Settings(), devices=devices, operations=operations)
        # The webhooks configured, as the server delivers them (server/bootstrap/plant.py).
        self._webhooks = webhooks_of(self.cell)
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(
            target=self._loop.run_forever, name="glue-cell", daemon=True
        )

    # --- lifecycle ---------------------------------------------------------

    def open(self, ready_timeout: float = 30.0) -> EmbeddedCell:
        """Start the cell and wait until it has left INITIALIZING."""
        self._thread.start()
        self._call(self._start())
        deadline = time.monotonic() + ready_timeout
        while self.get_current_state() is State.INITIALIZING and time.monotonic() < deadline:
            time.sleep(0.01)
        return self

    def close(self) -> None:
        """Halt the devices, stop the cell and its loop."""
        if self._thread.is_alive():
            self._call(stop_cell(self.cell, self._webhooks))
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=10)
        self._loop.close()

    async def _start(self) -> None:
        """The cell, then its webhooks (as the server's lifespan starts them)."""
        try:
            await self.cell.start()
        except BaseException:
            await self._webhooks.stop()
            raise
        assert self.cell.journal is not None
        self._webhooks.start(self.cell.view, self.cell.journal)

    def __enter__(self) -> EmbeddedCell:
        return self.open()

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # --- the specification's methods -------------------------------------

    def start(
        self, contourMatching: bool = True, workpiece_id: str | None = None
    ) -> tuple[bool, str]:
        """Begin trajectory execution; returns at once with (accepted, message)."""
        return self._command(Command.START, StartPayload(contourMatching, workpiece_id))

    def calibrateRobot(self, timeout: float = 120.0) -> tuple[bool, str, np.ndarray | None]:
        """Run robot calibration to its end; (success, message, annotated image or None)."""
        ok, message, _ = self._run_to_end(Command.CALIBRATE_ROBOT, State.CALIBRATING_ROBOT, timeout)
        stores = self.cell.stores
        if not ok or stores is None or not stores.calibration.robot_image_path.exists():
            return ok, message, None
        return ok, message, cv2.imread(str(stores.calibration.robot_image_path))

    def calibrateCamera(self, timeout: float = 120.0) -> tuple[bool, str]:
        """Run camera calibration to its end; (success, message)."""
        ok, message, _ = self._run_to_end(
            Command.CALIBRATE_CAMERA, State.CALIBRATING_CAMERA, timeout
        )
        return ok, message

    def createWorkpiece(self, timeout: float = 120.0) -> tuple[bool, Any]:
        """Create a workpiece from the camera; (success, result data or message)."""
        ok, message, result = self._run_to_end(
            Command.CREATE_WORKPIECE, State.CREATING_WORKPIECE, timeout
        )
        return ok, result if ok else message

    def emergency_stop(self) -> tuple[bool, str]:
        """Stop at once: valve closed, robot stopped, cell in ERROR."""
        return self._command(Command.ESTOP, StopPayload("embedded emergency_stop()"))

    def reset(self) -> tuple[bool, str]:
        """Leave ERROR for IDLE once every fault has cleared."""
        return self._command(Command.RESET)

    def pause(self) -> tuple[bool, str]:
        return self._command(Command.PAUSE)

    def resume(self) -> tuple[bool, str]:
        return self._command(Command.RESUME)

    def cancel(self) -> tuple[bool, str]:
        return self._command(Command.CANCEL)

    def get_current_state(self) -> State:
        return self.cell.view.state if self.cell.started else State.INITIALIZING

    def can_execute_operation(self, operation: str) -> bool:
        """Whether the named command would be accepted now (unknown names: False)."""
        canonical = normalize_command(operation)
        if canonical is None or not self.cell.started:
            return False
        return self.cell.view.allowed(canonical)[0]

    # --- plumbing ------------------------------------------------------------

    def _call(self, coroutine: Coroutine[Any, Any, T], timeout: float = 60.0) -> T:
        return asyncio.run_coroutine_threadsafe(coroutine, self._loop).result(timeout)

    def _command(self, command: Command, payload: Payload | None = None) -> tuple[bool, str]:
        outcome = self._call(self.cell.command(command, source="embedded", payload=payload))
        return outcome.accepted, outcome.message

    def _run_to_end(self, name: Command, state: State, timeout: float) -> tuple[bool, str, Any]:
        accepted, message = self._command(name)
        if not accepted:
            return False, message, None
        deadline = time.monotonic() + timeout
        while self.get_current_state() is state:
            if time.monotonic() > deadline:
                return False, f"{name} still running after {timeout:g} s", None
            time.sleep(0.01)
        view = self.cell.view
        if view.state is State.ERROR:
            return False, view.error_message or f"{name} failed", None
        return True, f"{name} completed", view.operation_result
