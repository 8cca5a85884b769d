"""Wear counters, the maintenance schedule and glue-line care on the simulated cell.

The cell is served over HTTP and reaches the robot and glue simulators through its
production clients, so what is counted is what the drivers really saw: the glue
simulator's own valve log and its integral of the flow are the reference. Long
histories (200 parts, a pot life run out, a reservoir nearly empty) are seeded into the
journal's `wear` table before the cell starts, as a cell that has worked that long
would have left it, so each test drives only the last step through the real path.
"""

from __future__ import annotations

import asyncio
import sqlite3
import time
from pathlib import Path
from typing import Any

import pytest

from server.drivers.sim.glue_sim import GlueSimulator
from server.settings.model import Settings
from server.storage.journal import Journal
from server.storage.journal import wear as wear_table
from tests.rig import SPRAY_DEMO, WAIT_S, Rig, open_rig, run

PURGE_AT = (350.0, 50.0, 120.0, 180.0, 0.0, 0.0)


def seed(data_path: Path, values: dict[str, float]) -> None:
    """The journal's wear rows as a cell that has worked a while left them."""
    path = Settings(data_path=data_path).journal_file
    journal = Journal(path)
    journal.open()  # creates the tables of a fresh journal
    connection = sqlite3.connect(path)
    with connection:
        for record in wear_table.records(values, time.time()):
            connection.execute(record.sql, record.params)
    connection.close()


async def maintenance(rig: Rig) -> dict[str, Any]:
    response = await rig.api.get("/maintenance")
    assert response.status_code == 200, response.text
    return response.json()


async def warnings(rig: Rig, code: str) -> list[dict[str, Any]]:
    await asyncio.sleep(0)
    response = await rig.api.get("/errors", params={"code": code})
    assert response.status_code == 200, response.text
    return response.json()["errors"]


async def until(predicate: Any, what: str) -> None:
    async with asyncio.timeout(WAIT_S):
        while not await predicate():
            await asyncio.sleep(0.02)


def openings(glue: GlueSimulator) -> int:
    return sum(1 for _, is_open in glue.valve_log if is_open)


async def test_a_run_counts_valve_cycles_and_glue_and_200_parts_make_the_nozzle_due(
    tmp_path: Path,
) -> None:
    async with open_rig(tmp_path) as rig:
        snapshot = await run(rig, "start", SPRAY_DEMO)
        assert snapshot["state"] == "IDLE", snapshot
        state = await maintenance(rig)
        counters = state["counters"]
        assert counters["parts"] == 1
        assert counters["valve_cycles"] == openings(rig.glue) > 0
        sim_ml = rig.glue.dispensed_ml
        assert sim_ml > 0
        # The driver counts the dispenser's own totaliser (the run's inspection waited for
        # its poll after the close): what the simulator dispensed, to the microlitre.
        assert counters["glue_ml"] == pytest.approx(sim_ml, abs=0.002)
        assert counters["travel_m"] > 0
        assert counters["camera_frames"] > 0
        nozzle = next(i for i in state["items"] if i["name"] == "clean nozzle")
        assert nozzle["status"] == "ok"
        kept_ml = counters["glue_ml"]
    # The counters survive the restart; a cell with 199 parts sprayed sprays one more.
    seed(tmp_path, {"parts": 199})
    async with open_rig(tmp_path) as rig:
        before = (await maintenance(rig))["counters"]
        assert before["parts"] == 199
        assert before["glue_ml"] == pytest.approx(kept_ml)
        assert await warnings(rig, "MAINTENANCE_DUE") == []
        await run(rig, "start", SPRAY_DEMO)
        state = await maintenance(rig)
        nozzle = next(i for i in state["items"] if i["name"] == "clean nozzle")
        assert state["counters"]["parts"] == 200
        assert nozzle["status"] == "due" and nozzle["percent"] == 100.0, nozzle
        rows = await warnings(rig, "MAINTENANCE_DUE")
        assert len(rows) == 1 and "clean nozzle" in rows[0]["message"], rows
        assert rows[0]["classification"] == "warning"
        # Done: its intervals start again, on record in the audit trail.
        response = await rig.api.post("/maintenance/clean nozzle/done")
        assert response.status_code == 200, response.text
        assert response.json()["status"] == "ok" and response.json()["percent"] == 0.0
        audit = (await rig.api.get("/audit")).json()["audit"]
        assert any("clean nozzle" in (row.get("detail") or "") for row in audit), audit
        assert (await rig.api.post("/maintenance/no such item/done")).status_code == 404


async def test_a_purge_moves_to_its_position_and_dispenses_as_set(tmp_path: Path) -> None:
    async with open_rig(
        tmp_path, purge_position=PURGE_AT, purge_seconds=0.4, purge_flow_ml_min=45.0
    ) as rig:
        response = await rig.api.post("/purge")
        assert response.status_code == 202, response.text
        assert response.json()["state"] == "IDLE"

        async def purged() -> bool:
            return (await maintenance(rig))["counters"]["purges"] == 1

        await until(purged, "the purge to end")
        assert rig.glue.valve_open is False
        assert openings(rig.glue) == 1
        (opened, _), (closed, shut) = list(rig.glue.valve_log)[-2:]
        assert shut is False and closed - opened >= 0.4
        assert rig.glue.status()["flow_setpoint_ml_min"] == pytest.approx(45.0)
        assert rig.glue.dispensed_ml > 0
        end = rig.robot.executed_path[-1].end
        assert list(end[:3]) == pytest.approx(PURGE_AT[:3], abs=0.5)
        state = await maintenance(rig)
        assert state["counters"]["valve_cycles"] == 1

        async def counted() -> bool:  # by the totaliser, at the monitor's next poll
            glue_ml = (await maintenance(rig))["counters"]["glue_ml"]
            return abs(glue_ml - rig.glue.dispensed_ml) <= 0.002

        await until(counted, "the purge's glue to be counted")
        assert (await rig.state())["state"] == "IDLE"


async def test_a_purge_outside_the_workspace_is_refused_and_nothing_moves(
    tmp_path: Path,
) -> None:
    outside = (400.0, 0.0, 5000.0, 180.0, 0.0, 0.0)
    async with open_rig(tmp_path, purge_position=outside) as rig:
        moves = len(rig.robot.executed_path)
        response = await rig.api.post("/purge")
        assert response.status_code == 409, response.text
        assert "purge position is outside the workspace" in response.json()["message"]
        assert len(rig.robot.executed_path) == moves
        assert openings(rig.glue) == 0


async def test_an_estop_during_a_purge_closes_the_valve(tmp_path: Path) -> None:
    async with open_rig(tmp_path, purge_position=PURGE_AT, purge_seconds=60.0) as rig:
        assert (await rig.api.post("/purge")).status_code == 202
        async with asyncio.timeout(WAIT_S):
            while not rig.glue.valve_open:
                await asyncio.sleep(0.005)
        response = await rig.api.post("/estop", json={"reason": "test"})
        assert response.status_code == 202, response.text
        await rig.wait_state("ERROR")
        assert rig.glue.valve_open is False
        worker = rig.cell.worker
        assert worker is not None
        async with asyncio.timeout(WAIT_S):
            while worker.activities.purging:
                await asyncio.sleep(0.01)
        assert rig.glue.valve_open is False
        assert (await maintenance(rig))["counters"]["purges"] == 1


async def test_a_start_after_the_pot_life_is_refused_naming_purge(tmp_path: Path) -> None:
    seed(tmp_path, {"mark:last_dispense_at": time.time() - 3600.0})
    async with open_rig(
        tmp_path, pot_life_minutes=30.0, purge_position=PURGE_AT, purge_seconds=0.2
    ) as rig:
        response = await rig.api.post("/start", json=SPRAY_DEMO)
        assert response.status_code == 409, response.text
        assert "purge" in response.json()["message"]
        assert (await rig.state())["state"] == "IDLE"
        assert openings(rig.glue) == 0
        state = await maintenance(rig)
        assert state["pot_life"]["status"] == "expired"

        async def warned() -> bool:
            return len(await warnings(rig, "POT_LIFE_EXCEEDED")) == 1

        await until(warned, "the pot life warning")
        # A purge restarts the pot life: the start is accepted.
        assert (await rig.api.post("/purge")).status_code == 202

        async def purged() -> bool:
            return (await maintenance(rig))["pot_life"]["status"] == "ok"

        await until(purged, "the purge to end")
        snapshot = await run(rig, "start", SPRAY_DEMO)
        assert snapshot["state"] == "IDLE"


async def test_a_low_glue_level_is_warned_and_a_refill_fills_it(tmp_path: Path) -> None:
    seed(tmp_path, {"glue_ml": 950.0})
    async with open_rig(tmp_path, glue_reservoir_ml=1000.0, glue_low_level_percent=10.0) as rig:
        state = await maintenance(rig)
        assert state["glue_level"]["status"] == "low"
        assert state["glue_level"]["level_ml"] == pytest.approx(50.0, abs=1.0)

        async def warned() -> bool:
            return len(await warnings(rig, "GLUE_LEVEL_LOW")) == 1

        await until(warned, "the glue level warning")
        response = await rig.api.post("/glue/refill")
        assert response.status_code == 200, response.text
        assert response.json()["status"] == "ok"
        assert response.json()["level_ml"] == pytest.approx(1000.0, abs=1.0)
