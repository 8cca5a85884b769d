"""The e-stop's halt has written both device frames when `halt_at_once` returns.

As ordinary tasks, the halt's commands would write their frames only at the loop's
next turn, behind every callback ready by then: a crowd's WebSocket writes, a vision
result, the requests queued ahead. Here the
production drivers talk to the simulators over loopback, and every write to a
socket is recorded as it happens.
"""

from __future__ import annotations

import asyncio
import json
from asyncio.selector_events import _SelectorSocketTransport
from collections.abc import AsyncIterator
from typing import Any

import pytest

from server.core.infra.eager import start_task
from server.core.operations.leash import Leash, leashed
from server.core.worker.devices import CellDevices
from server.core.worker.stop import halt_at_once
from server.drivers import glue_registers as regs
from server.drivers.glue_modbus import ModbusGlueDispenser
from server.drivers.robot_jsonrpc import JsonRpcRobot
from server.drivers.sim.glue_sim import GlueSimulator
from server.drivers.sim.robot_sim import RobotSimulator
from tests.fakes import FakeCamera

TIMEOUT = 2.0
WRITE_SINGLE_REGISTER = 6


@pytest.fixture
async def devices() -> AsyncIterator[CellDevices]:
    async with RobotSimulator(speed_factor=4) as robot_sim, GlueSimulator(seed=3) as glue_sim:
        robot = JsonRpcRobot("127.0.0.1", robot_sim.port, timeout=TIMEOUT)
        # No status poll of its own: one on the line would hold the close back.
        glue = ModbusGlueDispenser.tcp(
            "127.0.0.1", glue_sim.port, timeout=TIMEOUT, poll_interval=3600
        )
        await robot.connect()
        await glue.connect()
        try:
            yield CellDevices(robot, glue, FakeCamera())
        finally:
            await robot.close()
            await glue.close()


@pytest.fixture
def written(monkeypatch: pytest.MonkeyPatch) -> list[bytes]:
    """Every frame handed to a socket from here on, in order."""
    frames: list[bytes] = []
    write = _SelectorSocketTransport.write

    def recording(self: Any, data: Any) -> None:
        frames.append(bytes(data))
        write(self, data)

    monkeypatch.setattr(_SelectorSocketTransport, "write", recording)
    return frames


def _is_valve_close(frame: bytes) -> bool:
    return (
        len(frame) == 8
        and frame[1] == WRITE_SINGLE_REGISTER
        and int.from_bytes(frame[2:4], "big") == regs.VALVE_COMMAND.address
        and int.from_bytes(frame[4:6], "big") == regs.encode_valve(False)
    )


def _is_robot_stop(frame: bytes) -> bool:
    return json.loads(frame).get("method") == "stop"


async def test_both_halt_frames_are_on_their_sockets_when_the_halt_is_made(
    devices: CellDevices, written: list[bytes]
) -> None:
    halt = halt_at_once(devices, TIMEOUT)
    # No await yet: the loop has not turned since the halt was made.
    assert len(written) == 2, written
    assert _is_valve_close(written[0]) and _is_robot_stop(written[1])  # the valve first
    report = await halt
    assert report.valve_closed and report.robot_stopped and not report.errors


def _is_valve_write(frame: bytes, open_: bool) -> bool:
    return (
        len(frame) == 8
        and frame[1] == WRITE_SINGLE_REGISTER
        and int.from_bytes(frame[2:4], "big") == regs.VALVE_COMMAND.address
        and int.from_bytes(frame[4:6], "big") == regs.encode_valve(open_)
    )


async def test_an_opening_waiting_for_the_line_never_follows_the_halts_close(
    devices: CellDevices, written: list[bytes]
) -> None:
    """A halt's close goes ahead of what waits for the dispenser's line; a run's
    opening asked for before the stop and still waiting there must not go out after it.

    If it did, the valve would open again after the stop had closed it, the glue
    flowing until something closed it once more.
    """
    glue = devices.glue
    leash = Leash("run-1", glue)
    _, run_glue = leashed(devices.robot, glue, leash)
    poll = start_task(glue.read_status())  # on the line now, waiting for its answer
    opening = start_task(run_glue.set_valve(True))  # waiting for the line behind it
    leash.cut_now(halt_follows=True)  # as an e-stop does when it arrives (EmergencyStops.begin)
    report = await halt_at_once(devices, TIMEOUT)
    assert report.valve_closed and not report.errors
    results = await asyncio.gather(poll, opening, return_exceptions=True)
    closes = [i for i, frame in enumerate(written) if _is_valve_write(frame, False)]
    assert closes, written
    assert not any(_is_valve_write(frame, True) for frame in written[closes[0] :])
    assert (await glue.read_status()).valve_open is False
    assert isinstance(results[1], asyncio.CancelledError), results[1]  # as a cut leash's
