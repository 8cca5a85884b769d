"""Each fault's record names what it interrupted, on the served cell: the journal's row
(GET /errors and GET /errors/{seq}), the WebSocket-bound bus message and the log line
carry the operation, its run id and workpiece, and the stack when an exception
caused the fault. One test per way a run ends in ERROR, and one with no run."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from typing import Any

import pytest

from tests.rig import Rig, assert_safe, open_rig

FAULT_LOGGER = "server.core.worker.state_changes"


@pytest.fixture
async def rig(tmp_path) -> AsyncIterator[Rig]:
    """A fresh copy of the commissioned cell per test: each leaves its cell in ERROR."""
    async with open_rig(tmp_path) as running:
        yield running


async def running_run(rig: Rig) -> dict[str, Any]:
    """The run under way, once it is on its way to a workpiece."""
    async with asyncio.timeout(30):
        while True:
            operation = (await rig.state())["operation"]
            if operation and (operation.get("progress") or {}).get("workpiece_id"):
                return operation
            await asyncio.sleep(0.01)


async def newest_fault(rig: Rig, code: str) -> dict[str, Any]:
    """The newest fault row with `code`, as GET /errors/{seq} gives it."""
    rows = (await rig.api.get("/errors", params={"code": code, "limit": 1})).json()["errors"]
    assert rows, f"no {code} on record"
    response = await rig.api.get(f"/errors/{rows[0]['seq']}")
    assert response.status_code == 200
    one = response.json()
    assert one == rows[0]  # the list and the single fault agree
    return one


def fault_line(caplog: pytest.LogCaptureFixture, code: str) -> logging.LogRecord:
    found = [
        r
        for r in caplog.records
        if r.name == FAULT_LOGGER and r.getMessage().startswith(f"fault {code}")
    ]
    assert found, f"no fault line for {code}"
    return found[-1]


async def test_an_emergency_stop_names_the_run_it_stopped(
    rig: Rig, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.ERROR, FAULT_LOGGER)
    await rig.start_spraying()
    run = await running_run(rig)
    assert (
        await rig.api.post("/estop", json={"reason": "a hand near the nozzle"})
    ).status_code == 202
    await rig.wait_state("ERROR")
    fault = await newest_fault(rig, "EMERGENCY_STOP")
    context = fault["context"]
    assert context["operation"] == "trajectory" and context["run_id"] == run["run_id"]
    assert context["workpiece_id"] == "demo" and " of " in context["waypoint"]
    assert fault["trace"] == ""  # a person's stop, not an exception
    line = fault_line(caplog, "EMERGENCY_STOP")
    assert line.context["run_id"] == run["run_id"]  # type: ignore[attr-defined]


async def test_a_device_fault_in_a_run_carries_the_run_and_the_stack(
    rig: Rig, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.ERROR, FAULT_LOGGER)
    await rig.start_spraying()
    run = await running_run(rig)
    rig.robot.inject_fault("fail_next")  # the controller refuses the run's next command
    await assert_safe(rig, "robot")
    fault = await newest_fault(rig, "DEVICE_FAULT")
    assert fault["context"]["run_id"] == run["run_id"]
    assert fault["context"]["operation"] == "trajectory"
    assert fault["context"]["workpiece_id"] == "demo"
    # The stack runs from the operation down to the robot's client that raised.
    assert fault["trace"].startswith("Traceback (most recent call last):")
    assert "server/core/operations/" in fault["trace"]
    assert "server/drivers/robot_jsonrpc.py" in fault["trace"]
    line = fault_line(caplog, "DEVICE_FAULT")
    assert line.trace == fault["trace"]  # type: ignore[attr-defined]
    assert line.context["run_id"] == run["run_id"]  # type: ignore[attr-defined]


async def test_a_timed_out_run_names_itself(tmp_path) -> None:
    async with open_rig(tmp_path, processing_timeout=1.0, robot_speed_factor=1) as rig:
        await rig.start_spraying()
        run = await running_run(rig)
        await rig.wait_state("ERROR")
        fault = await newest_fault(rig, "OPERATION_TIMEOUT")
        assert fault["context"]["operation"] == "trajectory"
        assert fault["context"]["run_id"] == run["run_id"]


async def test_a_device_fault_with_no_run_says_so(tmp_path) -> None:
    async with open_rig(tmp_path, robot_heartbeat_interval=0.1) as rig:
        async with asyncio.timeout(10):  # the homing move done: nothing is asked of the robot
            while rig.robot.is_moving:
                await asyncio.sleep(0.05)
        rig.robot.inject_fault("stall")
        await assert_safe(rig, "robot")
        fault = await newest_fault(rig, "NO_ANSWER")
        assert fault["context"] == {"operation": None} and fault["trace"] == ""
        rig.robot.clear_faults()


async def test_an_unknown_fault_number_is_a_404_naming_it(rig: Rig) -> None:
    response = await rig.api.get("/errors/999999")
    assert response.status_code == 404 and "999999" in response.json()["detail"]
    assert (await rig.api.get("/errors/0")).status_code == 422
