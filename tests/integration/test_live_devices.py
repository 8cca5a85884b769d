"""Live device state through the whole server: `device` messages on /ws and /health,
with the robot and glue simulators behind the production clients."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Any

import pytest
from websockets.asyncio.client import ClientConnection, connect

from tests.rig import SPRAY_DEMO, Rig, open_rig


@pytest.fixture(scope="module")
def cell_data(tmp_path_factory: pytest.TempPathFactory):
    return tmp_path_factory.mktemp("cell")


@pytest.fixture
async def rig(cell_data) -> AsyncIterator[Rig]:
    async with open_rig(cell_data) as running:
        yield running


def live(rig: Rig, **query: str) -> connect:
    url = str(rig.api.base_url).replace("http", "ws", 1) + "/ws"
    if query:
        url += "?" + "&".join(f"{k}={v}" for k, v in query.items())
    return connect(url, additional_headers={"Authorization": rig.api.headers["authorization"]})


async def receive(ws: ClientConnection) -> dict[str, Any]:
    return json.loads(await asyncio.wait_for(ws.recv(), 10))


async def next_device(ws: ClientConnection) -> dict[str, Any]:
    while (message := await receive(ws))["type"] != "device":
        pass
    return message


async def test_device_messages_follow_the_valve_and_the_robot_during_a_run(rig: Rig) -> None:
    async with live(rig, types="device") as ws:
        assert (await receive(ws))["type"] == "snapshot"
        idle = await next_device(ws)  # pushed outside operations too, less often
        assert "seq" not in idle  # a sample, not a record: never replayed
        assert idle["glue"]["valve_open"] is False and idle["glue"]["connected"] is True
        assert (await rig.api.post("/start", json=SPRAY_DEMO)).status_code == 202
        seen_open, poses = False, set()
        async with asyncio.timeout(30):
            while not (seen_open and len(poses) > 3):
                message = await next_device(ws)
                glue, robot = message["glue"], message["robot"]
                assert glue["age_ms"] is not None
                seen_open = seen_open or glue["valve_open"] is True
                if glue["valve_open"]:
                    assert glue["flow_setpoint_ml_min"] > 0
                if robot["position"] is not None:  # none read yet before the run's first move
                    assert robot["age_ms"] is not None
                    poses.add(tuple(robot["position"]))
    health = (await rig.api.get("/health")).json()["devices"]
    assert health["glue"]["status_at"] and health["robot"]["position_at"]
    assert len(health["robot"]["position"]) == 6
    await rig.wait_state("IDLE", timeout=30)  # the module's next cell starts from IDLE


async def test_a_client_that_names_no_types_gets_no_samples(rig: Rig) -> None:
    async with live(rig) as ws:
        assert (await receive(ws))["type"] == "snapshot"
        assert (await rig.api.post("/start", json=SPRAY_DEMO)).status_code == 202
        async with asyncio.timeout(30):
            while (message := await receive(ws)).get("new_state") != "IDLE":
                assert message["type"] != "device"
                assert isinstance(message["seq"], int)


async def test_after_an_estop_the_read_back_valve_state_shows_at_once(rig: Rig) -> None:
    async with live(rig, types="state_changed,device") as ws:
        assert (await receive(ws))["type"] == "snapshot"
        await rig.start_spraying()
        async with asyncio.timeout(15):
            while not (await next_device(ws))["glue"]["valve_open"]:
                pass
        response = await rig.api.post("/estop", json={"reason": "test"})
        assert response.status_code == 202, response.text
        # GET /health at once: the close's own read-back, not the next status poll.
        glue = (await rig.api.get("/health")).json()["devices"]["glue"]
        assert glue["valve_open"] is False
        async with asyncio.timeout(10):
            while (await receive(ws)).get("new_state") != "ERROR":
                pass
        after = await receive(ws)  # pushed on the change of state, not at the next tick
        assert after["type"] == "device" and after["glue"]["valve_open"] is False
    assert rig.glue.valve_open is False
    assert (await rig.reset()).status_code == 202  # the module's next cell starts from IDLE
    await rig.wait_state("IDLE")
