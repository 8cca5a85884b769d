"""A reset that tells the truth, through the whole server, the real protocol
clients and the simulators: a request a stalled device swallowed before a reset
cannot fault the cell after it, the reset's probe is bounded by
reset_probe_timeout and never holds up an e-stop, and reset is not offered while
the drivers' monitoring knows a fault persists."""

from __future__ import annotations

import asyncio

import pytest

from server.drivers.robot_jsonrpc import JsonRpcRobot
from tests.rig import TIMEOUT, Rig, assert_safe, open_rig


@pytest.fixture(scope="module")
def cell_data(tmp_path_factory: pytest.TempPathFactory):
    """One data directory for the module: the simulated cell is commissioned once."""
    return tmp_path_factory.mktemp("cell")


async def robot_still(rig: Rig) -> None:
    """The homing move of the start-up done: nothing is asked of the robot any more."""
    async with asyncio.timeout(15):
        while rig.robot.is_moving:
            await asyncio.sleep(0.02)


async def swallowed(rig: Rig, before: int) -> None:
    """Until the stalled simulator has swallowed one more request than `before`."""
    async with asyncio.timeout(15):
        while rig.robot.ignored_while_stalled <= before:
            await asyncio.sleep(0.005)


async def test_a_request_swallowed_before_a_reset_cannot_fault_the_cell_after_it(
    cell_data,
) -> None:
    # The heartbeat asks a quiet link every 0.1 s and waits up to 3 s for the answer.
    async with open_rig(
        cell_data, robot_heartbeat_interval=0.1, robot_communication_timeout=3.0
    ) as rig:
        driver = rig.cell.devices.robot
        assert isinstance(driver, JsonRpcRobot)
        await robot_still(rig)
        rig.robot.inject_fault("stall")
        snapshot = await assert_safe(rig, "robot")
        assert snapshot["stop_reason"]["code"] == "NO_ANSWER"
        # The next heartbeat is swallowed too: its getPosition waits for an answer
        # that will never come, with nearly its whole timeout still to run.
        await swallowed(rig, rig.robot.ignored_while_stalled)
        stale = set(driver._pending)
        assert stale
        rig.robot.clear_faults()
        accepted = await rig.reset()
        assert accepted.status_code == 202, accepted.json()
        assert stale & set(driver._pending), "the swallowed request ended before the reset"
        async with asyncio.timeout(15):  # it times out now, in the session the reset began
            while stale & set(driver._pending):
                await asyncio.sleep(0.01)
        await asyncio.sleep(0.3)  # time for a fault it caused to reach the worker
        snapshot = await rig.state()
        assert snapshot["state"] == "IDLE" and snapshot["stop_reason"] is None, snapshot
        assert driver.health.active_faults == ()


async def test_reset_is_not_offered_while_the_robot_is_known_silent(cell_data) -> None:
    # No heartbeat for a minute: only the run's own requests find the stall.
    async with open_rig(cell_data, robot_heartbeat_interval=60) as rig:
        await rig.start_spraying()
        rig.robot.inject_fault("stall")
        await assert_safe(rig, "robot")
        allowed = (await rig.api.get("/operations/reset/allowed")).json()
        assert not allowed["allowed"] and "robot: no answer" in allowed["reason"], allowed
        assert "reset" not in (await rig.state())["available_commands"]
        health = (await rig.api.get("/health")).json()["devices"]["robot"]
        assert health["active_faults"] == [f"robot: no answer within {TIMEOUT:g} s"]
        rig.robot.clear_faults()
        # The monitoring's knowledge is not the last word: the live probe is.
        accepted = await rig.reset()
        assert accepted.status_code == 202, accepted.json()
        assert (await rig.api.get("/health")).json()["devices"]["robot"]["active_faults"] == []


async def test_the_reset_probe_is_bounded_by_its_setting(cell_data) -> None:
    # A controller given 30 s per request; the reset waits reset_probe_timeout only. The
    # probe renders a camera frame too, so the bound is one a frame meets on a busy machine
    # (beside a busy loop per core a frame takes longer than 0.5 s).
    async with open_rig(
        cell_data,
        robot_communication_timeout=30.0,
        robot_heartbeat_interval=60,
        reset_probe_timeout=5.0,
    ) as rig:
        await robot_still(rig)
        rig.robot.inject_fault("stall")
        await rig.api.post("/estop")
        await rig.wait_state("ERROR")
        refused = await rig.reset()
        assert refused.status_code == 409, refused.json()
        assert "robot: no answer in time (reset_probe_timeout 5 s)" in refused.json()["message"]
        assert (await rig.state())["state"] == "ERROR"
        rig.robot.clear_faults()
        accepted = await rig.reset()
        assert accepted.status_code == 202, accepted.json()


async def test_an_estop_during_the_reset_probe_is_decided_at_once(cell_data) -> None:
    async with open_rig(
        cell_data,
        robot_communication_timeout=30.0,
        robot_heartbeat_interval=60,
        reset_probe_timeout=5.0,
    ) as rig:
        await robot_still(rig)
        rig.robot.inject_fault("stall")
        await rig.api.post("/estop")  # its stop swallowed: HALT_INCOMPLETE, then ERROR
        await rig.wait_state("ERROR")
        before = rig.robot.ignored_while_stalled
        reset = asyncio.create_task(rig.reset())
        await swallowed(rig, before)  # the probe's getPosition: the probe is under way
        stop = await rig.api.post("/estop")
        assert stop.status_code == 202, stop.json()
        assert not reset.done(), "the e-stop waited for the reset's probe"
        refused = await reset
        assert refused.status_code == 409
        assert "overtaken by an emergency stop" in refused.json()["message"]
        assert (await rig.state())["state"] == "ERROR"
