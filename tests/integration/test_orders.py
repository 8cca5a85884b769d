"""Production orders on the simulated cell: a real server, real simulators, real journal.

An order runs its parts by itself from one POST /orders, each on a fresh part the
simulated camera presents; every stop holds it and only the operator resumes it.
Each part is inspected (server/quality/), with the robot at the speed its plan says
(`robot_speed_factor=1`), so each run takes the time a real arm's would.
"""

from __future__ import annotations

import asyncio
import csv
import io
from typing import Any

import pytest

from tests.rig import WAIT_S, Rig, open_rig

pytestmark = pytest.mark.asyncio


async def order_of(rig: Rig, order_id: str) -> dict:
    response = await rig.api.get(f"/orders/{order_id}")
    assert response.status_code == 200, response.text
    return response.json()


async def wait_order(rig: Rig, order_id: str, *states: str) -> dict:
    async with asyncio.timeout(WAIT_S * 3):
        while (order := await order_of(rig, order_id))["state"] not in states:
            await asyncio.sleep(0.05)
    return order


async def trajectory_runs(rig: Rig) -> list[dict]:
    rows = (await rig.api.get("/operations", params={"kind": "trajectory"})).json()
    return rows["operations"]


async def wait_running(rig: Rig) -> None:
    async with asyncio.timeout(WAIT_S):
        while not rig.glue.valve_open:
            await asyncio.sleep(0.005)


async def test_an_order_of_three_runs_to_completion_from_one_post(tmp_path) -> None:
    async with open_rig(tmp_path, robot_speed_factor=1) as rig:
        first_parts = list(rig.camera.scene.workpieces)
        created = await rig.api.post("/orders", json={"workpiece_id": "demo", "quantity": 3})
        assert created.status_code == 201, created.text
        order_id = created.json()["order"]["order_id"]
        assert created.json()["run_id"]
        order = await wait_order(rig, order_id, "completed", "held")
        assert order["state"] == "completed", order
        made = (order["good"], order["defective"], order["parts_made"])
        parts = [run.get("part") for run in await trajectory_runs(rig)]  # each one's verdict
        assert made == (3, 0, 3), (order, parts)
        assert (await rig.state())["state"] == "IDLE"
        # Fresh parts were laid on the table for the second and third runs.
        now_on_table = rig.camera.scene.workpieces
        assert now_on_table and not {id(p) for p in now_on_table} & {id(p) for p in first_parts}

        report = (await rig.api.get(f"/orders/{order_id}/report")).json()
        run_ids = [p["run_id"] for p in report["parts"]]
        assert len(set(run_ids)) == 3
        assert all(p["verdict"] == "good" and p["inspected"] for p in report["parts"])
        assert all(p["precision_mean_mm"] is not None and p["glue_ml"] for p in report["parts"])
        completed = {r["run_id"] for r in await trajectory_runs(rig) if r["outcome"] == "completed"}
        assert set(run_ids) <= completed
        text = (await rig.api.get(f"/orders/{order_id}/report", params={"format": "csv"})).text
        rows = list(csv.DictReader(io.StringIO(text)))
        assert [r["run_id"] for r in rows] == run_ids
        assert {r["verdict"] for r in rows} == {"good"}
        listed = (await rig.api.get("/orders")).json()
        assert listed["active"] is None and listed["orders"][0]["order_id"] == order_id


async def test_a_wrong_order_is_refused_naming_the_field_and_nothing_is_made(tmp_path) -> None:
    async with open_rig(tmp_path, robot_speed_factor=1) as rig:
        unknown = await rig.api.post("/orders", json={"workpiece_id": "no-such", "quantity": 2})
        assert unknown.status_code == 409 and unknown.json()["field"] == "workpiece_id"
        cases = [
            ({"workpiece_id": "demo", "quantity": 0}, "quantity"),
            ({"workpiece_id": "demo", "quantity": "3"}, "quantity"),
            ({"workpiece_id": "demo", "quantity": 2.5}, "quantity"),
            ({"quantity": 2}, "workpiece_id"),
        ]
        for body, field in cases:
            response = await rig.api.post("/orders", json=body)
            assert response.status_code == 422, (body, response.text)
            assert field in response.json()["detail"], response.json()
        assert (await rig.api.get("/orders")).json()["orders"] == []
        assert (await rig.state())["state"] == "IDLE" and await trajectory_runs(rig) == []
        assert (await rig.api.get("/orders/ord-00000000")).status_code == 404


async def test_close_ends_the_order_and_no_next_part_starts(tmp_path) -> None:
    async with open_rig(tmp_path, robot_speed_factor=1) as rig:
        created = await rig.api.post("/orders", json={"workpiece_id": "demo", "quantity": 50})
        order_id = created.json()["order"]["order_id"]
        closed = await rig.api.post(f"/orders/{order_id}/close")
        assert closed.status_code == 200 and closed.json()["state"] == "closed"
        await rig.wait_state("IDLE")
        await asyncio.sleep(1.0)  # a next part would have been started by now
        runs = await trajectory_runs(rig)
        assert len(runs) == 1, runs
        assert (await rig.api.post(f"/orders/{order_id}/resume")).status_code == 409
        audit = await rig.api.get("/audit", params={"action": f"POST /orders/{order_id}/close"})
        assert audit.status_code == 200 and audit.json()["total"] == 1, audit.json()


async def test_after_an_estop_the_order_is_held_until_resumed(tmp_path) -> None:
    async with open_rig(tmp_path, robot_speed_factor=1) as rig:
        created = await rig.api.post("/orders", json={"workpiece_id": "demo", "quantity": 2})
        order_id = created.json()["order"]["order_id"]
        await wait_running(rig)
        assert (await rig.api.post("/estop", json={"reason": "test"})).status_code == 202
        held = await wait_order(rig, order_id, "held")
        assert "run failed" in held["reason"] or "stopped" in held["reason"]
        assert held["defective"] == 1
        # While held after the stop, resume is refused: the cell is in ERROR.
        assert (await rig.api.post(f"/orders/{order_id}/resume")).status_code == 409
        assert (await rig.reset()).status_code == 202
        await rig.wait_state("IDLE")
        await asyncio.sleep(1.0)  # nothing continues by itself
        assert len(await trajectory_runs(rig)) == 1
        assert (await order_of(rig, order_id))["state"] == "held"
        # A start while the order is active makes its part; another workpiece is refused.
        refused = await rig.api.post("/start", json={"workpiece_id": "other-part"})
        assert refused.status_code == 409 and "workpiece_id" in refused.text
        # On record like every refusal: it had no event id, no event row and no audit row.
        event_id = refused.json()["event_id"]
        assert event_id and "is active and makes 'demo'" in refused.json()["message"]
        await asyncio.sleep(0.2)  # the audit row is written as the answer leaves
        events = (await rig.api.get("/events", params={"outcome": "refused"})).json()
        assert event_id in [row["id"] for row in events["events"]]
        audit = (await rig.api.get("/audit", params={"action": "POST /start"})).json()["audit"]
        assert any(event_id in (row["detail"] or "") for row in audit)
        resumed = await rig.api.post(f"/orders/{order_id}/resume")
        assert resumed.status_code == 200, resumed.text
        order = await wait_order(rig, order_id, "completed")
        assert (order["good"], order["defective"]) == (2, 1)


async def test_the_defect_limit_stops_the_cell_with_what_to_check(tmp_path) -> None:
    async with open_rig(tmp_path, order_defect_limit=2) as rig:
        created = await rig.api.post("/orders", json={"workpiece_id": "demo", "quantity": 5})
        order_id = created.json()["order"]["order_id"]
        for _ in range(2):
            await wait_running(rig)
            assert (await rig.api.post("/cancel")).status_code == 202
            await wait_order(rig, order_id, "held")
            await rig.wait_state("IDLE") if (await rig.state())["state"] != "ERROR" else None
            if (await order_of(rig, order_id))["defects_in_row"] < 2:
                assert (await rig.api.post(f"/orders/{order_id}/resume")).status_code == 200
        snapshot = await rig.wait_state("ERROR")
        reason = snapshot["stop_reason"]
        assert reason["code"] == "ORDER_DEFECT_LIMIT" and reason["component"] == "quality"
        assert "nozzle" in reason["message"] and "calibration" in reason["message"]
        assert not rig.glue.valve_open
        order = await order_of(rig, order_id)
        assert order["state"] == "held" and order["defects_in_row"] == 2


async def test_defective_parts_in_a_row_stop_the_cell(tmp_path) -> None:
    """A partly clogged nozzle: every part short of glue, judged by its inspection alone."""
    async with open_rig(tmp_path, robot_speed_factor=1, order_defect_limit=2) as rig:
        rig.glue.clog_nozzle(0.85)  # under the dispenser's own flow alarm: runs complete
        created = await rig.api.post("/orders", json={"workpiece_id": "demo", "quantity": 5})
        assert created.status_code == 201, created.text
        order_id = created.json()["order"]["order_id"]
        snapshot = await rig.wait_state("ERROR", timeout=WAIT_S * 3)
        assert snapshot["stop_reason"]["code"] == "ORDER_DEFECT_LIMIT"
        assert not rig.glue.valve_open
        order = await order_of(rig, order_id)
        assert (order["state"], order["good"], order["defective"]) == ("held", 0, 2)
        report = (await rig.api.get(f"/orders/{order_id}/report")).json()
        assert [p["verdict"] for p in report["parts"]] == ["defective", "defective"]
        assert all(p["reasons"] for p in report["parts"]), report


async def test_a_restart_leaves_the_order_held(tmp_path) -> None:
    async with open_rig(tmp_path, robot_speed_factor=1) as rig:
        created = await rig.api.post("/orders", json={"workpiece_id": "demo", "quantity": 5})
        order_id = created.json()["order"]["order_id"]
        await wait_running(rig)
    async with open_rig(
        tmp_path, robot_speed_factor=1, wait_idle=False
    ) as rig:  # stopped mid-part, started again
        await rig.wait_state("ERROR")
        order = await order_of(rig, order_id)
        assert order["state"] == "held", order
        await asyncio.sleep(1.0)
        runs = await trajectory_runs(rig)
        assert len(runs) == 1 and runs[0]["outcome"] == "interrupted"
        # The part cut short is the order's first, defective; it had vanished from the
        # order (and its run counted no workpiece, so the KPIs missed a failed one).
        assert (order["parts_made"], order["defective"], order["good"]) == (1, 1, 0), order
        report = (await rig.api.get(f"/orders/{order_id}/report")).json()
        assert [p["run_id"] for p in report["parts"]] == [runs[0]["run_id"]]
        assert "the server stopped" in report["parts"][0]["reasons"][0]
        assert runs[0]["workpieces"] == 1
        assert (await rig.api.get("/kpis")).json()["workpieces_failed"] == 1
        assert (await rig.reset()).status_code == 202
        await rig.wait_state("IDLE")
        await asyncio.sleep(1.0)  # nor after the reset
        assert len(await trajectory_runs(rig)) == 1
        assert (await order_of(rig, order_id))["state"] == "held"


async def test_a_restart_counts_the_paused_part_of_a_held_order(tmp_path) -> None:
    """A paused order's part is still to finish; a restart ends that part and holds it."""
    async with open_rig(tmp_path, robot_speed_factor=1) as rig:
        created = await rig.api.post("/orders", json={"workpiece_id": "demo", "quantity": 5})
        order_id = created.json()["order"]["order_id"]
        await wait_running(rig)
        assert (await rig.api.post("/pause")).status_code == 202
        async with asyncio.timeout(WAIT_S):
            while "paused" not in str((await order_of(rig, order_id))["reason"]):
                await asyncio.sleep(0.05)
    async with open_rig(tmp_path, robot_speed_factor=1, wait_idle=False) as rig:
        await rig.wait_state("ERROR")
        order = await order_of(rig, order_id)
        assert order["state"] == "held"
        assert (order["parts_made"], order["defective"]) == (1, 1), order


async def test_a_part_cut_short_counts_toward_the_defect_limit_and_a_closed_order(
    tmp_path,
) -> None:
    """The part a restart counts is a defective part like any: at the defect limit the
    order is held with that reason (a resume made one more part past it), and a closed
    order whose last run was cut short gets that part too."""
    async with open_rig(tmp_path, robot_speed_factor=1, order_defect_limit=1) as rig:
        limited = await rig.api.post("/orders", json={"workpiece_id": "demo", "quantity": 5})
        limited_id = limited.json()["order"]["order_id"]
        await wait_running(rig)
    async with open_rig(tmp_path, robot_speed_factor=1, wait_idle=False) as rig:
        await rig.wait_state("ERROR")
        order = await order_of(rig, limited_id)
        assert order["state"] == "held" and "defective parts in a row" in order["reason"], order
        assert (await rig.reset()).status_code == 202
        await rig.wait_state("IDLE")
        closed = await rig.api.post(f"/orders/{limited_id}/close")
        assert closed.status_code == 200, closed.text
        other = await rig.api.post("/orders", json={"workpiece_id": "demo", "quantity": 5})
        other_id = other.json()["order"]["order_id"]
        await wait_running(rig)
        assert (await rig.api.post(f"/orders/{other_id}/close")).status_code == 200
    async with open_rig(tmp_path, robot_speed_factor=1, wait_idle=False) as rig:
        await rig.wait_state("ERROR")
        order = await order_of(rig, other_id)
        assert order["state"] == "closed" and order["parts_made"] == 1, order


async def test_gluectl_order_start_show_list_report_close_resume(tmp_path) -> None:
    from tests.integration.test_gluectl import gluectl_process

    async with open_rig(tmp_path, robot_speed_factor=1) as rig:
        base = ("--url", str(rig.api.base_url).rstrip("/"), "--data-dir", str(tmp_path))

        async def cli(*args: str) -> Any:
            return await gluectl_process(*base, *args)

        bad = await cli("order", "start", "no-such-part", "2")
        assert bad.code == 3 and "workpiece_id" in bad.stderr, bad
        started = await cli("--json", "order", "start", "demo", "2")
        assert started.code == 0, started.stderr
        order_id = started.json()["order"]["order_id"]
        await wait_order(rig, order_id, "completed")
        shown = await cli("order", "show", order_id)
        assert shown.code == 0 and "2 of 2" in shown.stdout and "completed" in shown.stdout
        listed = await cli("order", "list")
        assert listed.code == 0 and order_id in listed.stdout
        report = await cli("order", "report", order_id)
        assert report.code == 0 and report.stdout.count("good") >= 2, report.stdout
        as_csv = await cli("order", "report", order_id, "--csv")
        assert as_csv.code == 0 and len(as_csv.stdout.strip().splitlines()) == 3
        assert (await cli("order", "close", order_id)).code == 3  # completed: refused (409)
        assert (await cli("order", "resume", order_id)).code == 3
        second = (await cli("--json", "order", "start", "demo", "40")).json()["order"]
        closed = await cli("order", "close", second["order_id"])
        assert closed.code == 0 and "closed" in closed.stdout
