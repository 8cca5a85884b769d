"""The specification's in-process API over the same core."""

from __future__ import annotations

import time

from server.core.machine.transitions import State
from server.core.worker.devices import CellDevices
from server.embedded.facade import EmbeddedCell, blocking_operation
from server.settings.model import Settings
from tests.conftest import demo_stores
from tests.fakes import FakeCamera, FakeGlue, FakeRobot


def wait_for(cell: EmbeddedCell, state: State, timeout: float = 10) -> None:
    deadline = time.monotonic() + timeout
    while cell.get_current_state() is not state:
        assert time.monotonic() < deadline, f"never reached {state}"
        time.sleep(0.005)


def test_spec_methods_and_return_shapes(tmp_path) -> None:
    glue = FakeGlue()
    devices = CellDevices(FakeRobot(speed_factor=10), glue, FakeCamera())
    settings = Settings(emergency_stop_timeout=0.5, data_path=tmp_path)
    demo_stores(tmp_path)
    with EmbeddedCell(settings, devices=devices) as cell:
        assert cell.get_current_state() is State.IDLE
        assert cell.can_execute_operation("calibrate-robot") is True
        # A plain start matches parts on the table: not without a robot calibration.
        assert cell.can_execute_operation("start") is False
        assert cell.can_execute_operation("resume") is False
        assert cell.can_execute_operation("no-such-thing") is False
        ok, message = cell.start(contourMatching=False, workpiece_id="demo")
        assert ok is True and "EXECUTING_TRAJECTORY" in message
        assert cell.start() == (False, "start is not allowed in EXECUTING_TRAJECTORY")
        ok, message = cell.emergency_stop()
        assert ok and cell.get_current_state() is State.ERROR and glue.valve_open is False
        assert cell.reset()[0] is True
        wait_for(cell, State.IDLE)


def test_an_existing_application_method_serves_as_an_operation(tmp_path) -> None:
    calls = []

    def legacy_calibrate_camera() -> dict:
        calls.append("called")
        return {"reprojection_error_px": 0.12}

    devices = CellDevices(FakeRobot(), FakeGlue(), FakeCamera())
    operations = {"calibrate_camera": blocking_operation(legacy_calibrate_camera)}
    with EmbeddedCell(Settings(data_path=tmp_path), devices=devices, operations=operations) as cell:
        assert cell.calibrateCamera() == (True, "calibrate-camera completed")
        assert calls == ["called"]
        assert cell.cell.view.operation_result == {"reprojection_error_px": 0.12}
