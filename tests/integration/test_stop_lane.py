"""The e-stop's devices are commanded as its request passes the gate (server/api/stop_lane.py).

Commanded by the route's handler, after FastAPI has routed the request and read and
validated its body, a stop whose body is slow to arrive (a loaded client, a lossy
link) would stop nothing until the body was complete.
"""

from __future__ import annotations

import asyncio
import json
from urllib.parse import urlsplit

import httpx
import pytest

from server.api import audit, commands
from server.bootstrap.cell import Cell
from server.core.machine.transitions import State
from server.core.worker.devices import CellDevices
from server.settings.model import Settings
from tests.fakes import FakeCamera, FakeGlue, FakeRobot
from tests.serving import admin_headers, serve

BODY = json.dumps({"reason": "hand in the cell"}).encode()


async def _stop_with_a_late_body(
    url: str, token_header: str
) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """Send POST /estop's headers now and keep its body back."""
    parts = urlsplit(url)
    reader, writer = await asyncio.open_connection(parts.hostname, parts.port)
    head = (
        "POST /estop HTTP/1.1\r\n"
        f"Host: {parts.netloc}\r\n"
        f"Authorization: {token_header}\r\n"
        "Content-Type: application/json\r\n"
        f"Content-Length: {len(BODY)}\r\n\r\n"
    )
    writer.write(head.encode())
    await writer.drain()
    return reader, writer


async def test_a_stop_halts_the_devices_before_its_body_has_arrived(
    fast_settings: Settings,
) -> None:
    robot, glue = FakeRobot(50), FakeGlue()
    cell = Cell(fast_settings, devices=CellDevices(robot, glue, FakeCamera()))
    async with serve(cell) as url:
        stops_before, closes_before = robot.stops, len(glue.valve_log)
        header = admin_headers(fast_settings.data_path)["Authorization"]
        reader, writer = await _stop_with_a_late_body(url, header)
        async with asyncio.timeout(5):
            while robot.stops == stops_before or len(glue.valve_log) == closes_before:
                await asyncio.sleep(0.005)
        assert glue.valve_log[-1][1] is False  # the valve commanded closed
        writer.write(BODY)
        await writer.drain()
        status_line = await reader.readline()
        await reader.read(65536)
        writer.close()
        assert b" 202 " in status_line
        assert cell.view.state is State.ERROR
        assert cell.worker is not None and "hand in the cell" in cell.worker.ctx.stop_reason.message
        assert robot.stops == stops_before + 1  # the route made the stop with the lane's halt


async def test_a_stop_the_gate_refuses_commands_nothing(fast_settings: Settings) -> None:
    robot, glue = FakeRobot(50), FakeGlue()
    cell = Cell(fast_settings, devices=CellDevices(robot, glue, FakeCamera()))
    async with serve(cell) as url, httpx.AsyncClient(base_url=url, timeout=10) as client:
        stops_before, valve_before = robot.stops, len(glue.valve_log)
        answer = await client.post("/estop", headers={"Authorization": "Bearer not-a-token"})
        assert answer.status_code == 401
        assert (robot.stops, len(glue.valve_log)) == (stops_before, valve_before)
        assert cell.view.state is State.IDLE


async def test_a_stop_whose_route_fails_is_still_made(
    fast_settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The lane's halt never stays without its transition: the cell goes to ERROR.

    An invalid body goes on to the route (its 422), which finishes the stop there."""

    async def broken(*_args: object, **_kwargs: object) -> None:
        raise RuntimeError("a defect on the route's way")

    monkeypatch.setattr(commands, "_stop", broken)
    assert await _robot_stops_of_a_failing_stop(fast_settings, {"reason": 5}) >= 1


async def test_a_stop_whose_lane_fails_after_its_halt_is_still_made(
    fast_settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A defect between the halt and the stop's event (here the audit note) still leaves
    the cell in ERROR, the stop on record: the lane posts the event on its way out."""

    def broken(*_args: object, **_kwargs: object) -> None:
        raise RuntimeError("a defect on the lane's way")

    monkeypatch.setattr(audit, "note", broken)
    assert await _robot_stops_of_a_failing_stop(fast_settings, {"reason": "x"}) == 1


async def _robot_stops_of_a_failing_stop(settings: Settings, body: dict[str, object]) -> int:
    """POST /estop with `body` where a defect makes it a 500: the cell still goes to
    ERROR on the e-stop; how many stops the robot was sent."""
    robot = FakeRobot(50)
    cell = Cell(settings, devices=CellDevices(robot, FakeGlue(), FakeCamera()))
    async with serve(cell) as url, httpx.AsyncClient(base_url=url, timeout=10) as client:
        stops_before = robot.stops
        answer = await client.post("/estop", json=body, headers=admin_headers(settings.data_path))
        assert answer.status_code == 500
        async with asyncio.timeout(5):
            while cell.view.state is not State.ERROR:
                await asyncio.sleep(0.005)
        assert cell.worker is not None and cell.worker.ctx.stop_reason.code == "EMERGENCY_STOP"
        return robot.stops - stops_before
