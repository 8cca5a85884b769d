"""Device faults injected at random points of an operation, through the whole
server and the real protocol clients.

tests/integration/test_device_faults.py puts each fault at one fixed point
(spraying has begun). A fault can land anywhere: between two waypoints, while
the valve opens, during a capture, while the arm goes home after the run. Each
round here starts an operation, waits a random time within the operation's
measured duration and injects the fault, then checks what must hold wherever
it landed: the cell ends in ERROR naming the device, the valve is closed, the
robot is still, a reset is refused while the fault lasts and accepted once it
is gone. A fault that only shows when the device is used (a stalled robot, a
failed camera) and landed after the run is brought out by using the device.

Rounds that landed mid-operation are counted, and each kind must have at least
one, or the randomness proved nothing. The seed is fixed and printed; set
RANDOM_FAULTS_SEED to replay another.

Each kind runs on its own copy of a cell commissioned once for the module: ERROR
is latched across a restart, so a kind that failed with its cell in ERROR would
otherwise fail every later kind's setup too. A round checks that the cell had
not faulted on its own before the fault was injected: a fault it did not cause
would otherwise be judged as its own (its halt's stop, sent before the round
read the robot's stop count, once looked like a halt that sent none).
"""

from __future__ import annotations

import asyncio
import os
import random
import shutil
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import pytest

from server.core.machine.transitions import OPERATIONAL_STATES
from tests.rig import (
    DEVICE_FAULTS,
    SPRAY_DEMO,
    TIMEOUT,
    WAIT_S,
    DeviceFaultKind,
    Rig,
    assert_safe,
    open_rig,
)

ROUNDS = 3  # per fault kind, bounded for CI
SEED = int(os.environ.get("RANDOM_FAULTS_SEED", "20260517"))
WINDOW = 0.8  # faults land within this fraction of the operation's measured duration
OPERATIONAL = {state.value for state in OPERATIONAL_STATES}
# Bound on a fault being noticed or an operation ending (a camera calibration is
# CPU-bound): not a performance assertion, so sized for a machine busy with other work.
SETTLE_S = TIMEOUT * 3 + WAIT_S


@pytest.fixture(scope="module")
def commissioned(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A data directory whose simulated cell was commissioned once, and left IDLE."""
    path = tmp_path_factory.mktemp("commissioned")

    async def commission() -> None:
        async with open_rig(path):
            pass

    asyncio.run(commission())
    return path


@pytest.fixture
async def rig(commissioned: Path, tmp_path: Path) -> AsyncIterator[Rig]:
    """The rig on this test's own copy of the commissioned cell."""
    data = shutil.copytree(commissioned, tmp_path / "cell")
    async with open_rig(data) as running:
        yield running


async def until(condition: Callable[[], bool], what: str) -> None:
    """Wait for `condition`; fail naming `what` if it does not come within SETTLE_S."""
    try:
        async with asyncio.timeout(SETTLE_S):
            while not condition():
                await asyncio.sleep(0.01)
    except TimeoutError:
        raise AssertionError(f"{what} never came (waited {SETTLE_S:g} s)") from None


async def settled(rig: Rig) -> dict:
    """The state once the running operation has ended, one way or the other."""
    async with asyncio.timeout(SETTLE_S):
        while (snapshot := await rig.state())["state"] in OPERATIONAL:
            await asyncio.sleep(0.01)
    return snapshot


async def clean_run(rig: Rig, operation: str) -> float:
    """Run `operation` without a fault; seconds from `begin` returning to its end."""
    await rig.begin(operation)
    started = time.monotonic()
    snapshot = await settled(rig)
    assert snapshot["state"] == "IDLE", snapshot
    assert snapshot["operation_result"] is not None, snapshot
    return time.monotonic() - started


async def reach_error(rig: Rig, fault: DeviceFaultKind) -> tuple[dict, bool]:
    """Wait for the fault to put the cell in ERROR; True if it had to be brought out.

    A fault that landed after the run is noticed in IDLE by the drivers that
    watch their link; the others show at the next use of the device.
    """
    snapshot = await settled(rig)
    if snapshot["state"] == "ERROR":
        return snapshot, False
    assert snapshot["state"] == "IDLE", snapshot
    if fault.noticed_when_idle:
        return await rig.wait_state("ERROR", timeout=SETTLE_S), False
    # Using the device brings it out; 409 if the homing move already did.
    if fault.operation == "spray":
        response = await rig.api.post("/start", json=SPRAY_DEMO)
    else:
        response = await rig.api.post(f"/{fault.operation}")
    assert response.status_code in (202, 409), response.json()
    return await rig.wait_state("ERROR", timeout=SETTLE_S), True


async def fault_round(rig: Rig, fault: DeviceFaultKind, delay: float) -> bool:
    """One fault at `delay` s into the operation; True if it landed mid-operation."""
    await rig.begin(fault.operation)
    await asyncio.sleep(delay)
    stops = rig.robot.stop_received_count
    before = rig.cell.worker.view.snapshot()  # in this process: no await before the fault
    assert before["state"] != "ERROR", f"the cell faulted before the injection: {before}"
    fault.inject(rig)
    snapshot, brought_out = await reach_error(rig, fault)
    snapshot = await assert_safe(rig, fault.component)  # named, and the robot is still
    reason = snapshot["stop_reason"]
    assert reason["code"] in fault.codes, reason
    assert reason["message"], reason
    if fault.valve_closes_at_once:
        assert rig.glue.valve_open is False, "the valve is open in ERROR"
    if fault.stop_reaches_robot:  # the simulator counts each stop it reads, stalled or not
        await until(lambda: rig.robot.stop_received_count > stops, "the halt's stop")

    refused = await rig.reset()
    assert refused.status_code == 409, refused.json()
    assert fault.refusal in refused.json()["message"], refused.json()
    assert (await rig.state())["state"] == "ERROR"

    fault.clear(rig)
    if fault.component == "robot" and not fault.stop_reaches_robot:
        # A dropped link comes back by itself, refused reset or not.
        robot = rig.cell.devices.robot
        async with asyncio.timeout(SETTLE_S):
            while not robot.health.connected:
                await asyncio.sleep(0.05)
    accepted = await rig.reset()
    assert accepted.status_code == 202, accepted.json()
    after = await rig.wait_state("IDLE")
    assert after["stop_reason"] is None, after
    assert rig.glue.valve_open is False, "the valve is open after the reset"
    return not brought_out and snapshot["previous_state"] in OPERATIONAL


@pytest.mark.parametrize("kind", list(DEVICE_FAULTS))
async def test_fault_at_random_points(rig: Rig, kind: str) -> None:
    fault = DEVICE_FAULTS[kind]
    rng = random.Random(f"{SEED}:{kind}")
    duration = await clean_run(rig, fault.operation)
    print(f"{kind}: seed {SEED}, operation {fault.operation} takes {duration:.2f} s")
    landed = 0
    for number in range(1, ROUNDS + 1):
        delay = rng.uniform(0.0, WINDOW * duration)
        mid_operation = await fault_round(rig, fault, delay)
        landed += mid_operation
        where = "mid-operation" if mid_operation else "after the operation"
        print(f"{kind}: round {number}: fault at {delay:.3f} s landed {where}")
    assert landed >= 1, f"no {kind} fault landed mid-operation in {ROUNDS} rounds (seed {SEED})"
