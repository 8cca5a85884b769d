"""One verdict per part, on every path, on the served cell.

Three real parts, sprayed on the rig's simulators by two production orders: a part
short of glue (a partly clogged nozzle: inspected, defective), a part stopped by STOP
mid-run (defective, not inspected, saying why), and a clean part (inspected, good).
Each path that tells the plant or a person about parts must give each the same verdict
and the same words, and count them alike: the order (GET /orders, its report), the
Last part card's source (GET /operations' `part`), GET /kpis, the operations CSV
export, Prometheus, MQTT (Debian's mosquitto: the `run` messages and the retained
`kpis`), OPC UA (asyncua's own Client: PackML Admin's ProdProcessedCount and
ProdDefectiveCount) and webhooks (a receiver on loopback: `part` and `run_completed`).
"""

from __future__ import annotations

import asyncio
import csv
import io
from pathlib import Path
from typing import Any

from tests.integration.test_part_verdicts import metric, until_counts
from tests.integration.test_webhooks import (
    RECEIVER_ON_THIS_HOST,
    Receiver,
    hook,
    receiving,
    until,
)
from tests.mosquitto import mosquitto, subscriber
from tests.rig import WAIT_S, Rig, open_rig
from tests.serving import free_port

CELL = "cell-q"  # the OPC UA helpers of test_part_verdicts address this cell
BASE = f"glue/{CELL}"
STOPPED = "run stopped: emergency stop (STOP)"


async def order_of(rig: Rig, order_id: str) -> dict[str, Any]:
    response = await rig.api.get(f"/orders/{order_id}")
    assert response.status_code == 200, response.text
    return response.json()


async def until_order(rig: Rig, order_id: str, check: Any) -> dict[str, Any]:
    async with asyncio.timeout(WAIT_S * 3):
        while not check(order := await order_of(rig, order_id)):
            await asyncio.sleep(0.05)
    return order


async def make_three_parts(rig: Rig) -> tuple[str, str, str]:
    """A defective part and a stopped one (the first order), then a good one (the
    second); their run ids in that order."""
    rig.glue.clog_nozzle(0.85)  # under the dispenser's own flow alarm: the run completes
    created = await rig.api.post("/orders", json={"workpiece_id": "demo", "quantity": 2})
    assert created.status_code == 201, created.text
    first, short = created.json()["order"]["order_id"], created.json()["run_id"]
    # The order starts its next part by itself: STOP it once it is under way.
    await until_order(rig, first, lambda o: o["parts_made"] == 1)
    async with asyncio.timeout(WAIT_S):
        while True:
            snapshot = await rig.state()
            run = (snapshot.get("operation") or {}).get("run_id")
            if snapshot["state"] == "EXECUTING_TRAJECTORY" and run and run != short:
                break
            await asyncio.sleep(0.01)
    stopped = run
    assert (await rig.api.post("/estop")).status_code in (200, 202)
    await rig.wait_state("ERROR")
    assert (await rig.reset()).status_code == 202
    await rig.wait_state("IDLE")
    closed = await rig.api.post(f"/orders/{first}/close")
    assert closed.status_code == 200, closed.text
    rig.glue.clog_nozzle(1.0)
    created = await rig.api.post("/orders", json={"workpiece_id": "demo", "quantity": 1})
    assert created.status_code == 201, created.text
    second, good = created.json()["order"]["order_id"], created.json()["run_id"]
    done = await until_order(rig, second, lambda o: o["state"] in ("completed", "held"))
    assert done["state"] == "completed", done
    await rig.wait_state("IDLE")
    return short, stopped, good


def part_counts(kpis: dict[str, Any]) -> tuple[Any, Any, Any]:
    """The parts of a KPI document (GET /kpis, MQTT's `kpis`): good, defective, not inspected."""
    quality = kpis.get("quality") or {}
    keys = ("parts_good", "parts_defective", "parts_not_inspected")
    good, defective, not_inspected = (quality.get(key) for key in keys)
    return good, defective, not_inspected


def words(part: dict[str, Any]) -> tuple[str, bool, str, str]:
    """What must agree on every path: verdict, inspected, label, first reason."""
    reasons = part["reasons"]
    if isinstance(reasons, str):  # the CSV's " | "-joined column
        reasons = reasons.split(" | ") if reasons else []
    first = reasons[0] if reasons else ""
    inspected = part["inspected"]
    if isinstance(inspected, str):
        inspected = inspected == "yes"
    return part["verdict"], inspected, part.get("label") or "", first


async def test_each_part_has_one_verdict_on_every_path(tmp_path: Path) -> None:
    opcua_port = free_port()
    receiver = Receiver()
    with mosquitto(tmp_path / "broker") as broker:
        async with receiving(receiver) as url:
            overrides = {
                "cell_id": CELL,
                **broker.cell_login,
                "opcua_endpoint": f"opc.tcp://127.0.0.1:{opcua_port}",
                "opcua_admin_interval": 1,
                "mqtt_kpis_interval": 1,
                "order_defect_limit": 5,
                "webhooks": [hook(url, "mes", ["part", "run_completed"])],
                **RECEIVER_ON_THIS_HOST,
            }
            async with (
                open_rig(tmp_path / "data", robot_speed_factor=1, **overrides) as rig,
                subscriber(broker.port, f"{BASE}/#") as plant,
            ):
                short, stopped, good = await make_three_parts(rig)
                runs = (short, stopped, good)

                # The Last part card's source: GET /operations' `part`, judged once.
                rows = (await rig.api.get("/operations", params={"kind": "trajectory"})).json()
                part_of = {r["run_id"]: r["part"] for r in rows["operations"]}
                expected = {run: words(part_of[run]) for run in runs}
                verdict_short, inspected_short, label_short, why_short = expected[short]
                assert (verdict_short, inspected_short, label_short) == (
                    "defective",
                    True,
                    "defective",
                ), part_of[short]
                assert "glue" in why_short or "flow" in why_short, part_of[short]
                assert expected[stopped] == (
                    "defective",
                    False,
                    "defective (not inspected)",
                    STOPPED,
                ), part_of[stopped]
                assert expected[good] == ("good", True, "good", ""), part_of[good]

                # The order card: the orders' counts and their reports' parts.
                first, second = (await rig.api.get("/orders")).json()["orders"][::-1]
                assert (first["good"], first["defective"], first["not_inspected"]) == (0, 2, 0)
                assert (second["good"], second["defective"], second["not_inspected"]) == (1, 0, 0)
                reported: dict[str, Any] = {}
                for order in (first, second):
                    report = (await rig.api.get(f"/orders/{order['order_id']}/report")).json()
                    reported |= {p["run_id"]: p for p in report["parts"]}
                for run in runs:
                    verdict, inspected, _, why = words(reported[run])
                    assert (verdict, inspected, why) == (
                        expected[run][0],
                        expected[run][1],
                        expected[run][3],
                    ), reported[run]

                # GET /kpis: three parts, two defective (the stopped one among them).
                kpis = (await rig.api.get("/kpis")).json()
                quality = kpis["quality"]
                counts = part_counts(kpis)
                assert counts == (1, 2, 0), quality
                assert kpis["oee"]["quality"] == 1 / 3

                # The operations CSV export: each part's verdict columns.
                export = await rig.api.get("/export/operations.csv", params={"kind": "trajectory"})
                assert export.status_code == 200, export.text
                exported = {r["run_id"]: r for r in csv.DictReader(io.StringIO(export.text))}
                for run in runs:
                    verdict, inspected, _, why = words(exported[run])
                    assert (verdict, inspected, why) == (
                        expected[run][0],
                        expected[run][1],
                        expected[run][3],
                    ), exported[run]

                # Prometheus: every part by its verdict.
                text = (await rig.api.get("/metrics")).text
                assert metric(text, 'glue_cell_parts_total{verdict="good"}') == 1
                assert metric(text, 'glue_cell_parts_total{verdict="defective"}') == 2
                assert metric(text, 'glue_cell_parts_total{verdict="not_inspected"}') == 0

                # OPC UA: PackML Admin's counts, as /kpis says them.
                await until_counts(opcua_port, (3, 2))

                # MQTT: each run's message; the retained kpis.
                told = await plant.wait(
                    lambda: (r := plant.on(f"{BASE}/run")) and len(r) >= 3 and r
                )
                by_run = {m["run_id"]: m for m in told if m["operation"] == "trajectory"}
                assert {run: words(by_run[run]) for run in runs} == expected
                # Retained and periodic: the plant hears /kpis' counts within a tick.
                await plant.wait(lambda: part_counts(plant.on(f"{BASE}/kpis")[-1]) == counts)

                # Webhooks: a part notice for each part; run_completed for the two that did.
                await until(lambda: len(receiver.notices("part")) >= 3)
                noticed = {n["run_id"]: n for n in receiver.notices("part")}
                assert {run: words(noticed[run]) for run in runs} == expected
                completed = {n["run_id"]: n for n in receiver.notices("run_completed")}
                assert set(completed) == {short, good}
                assert {run: words(completed[run]) for run in (short, good)} == {
                    run: expected[run] for run in (short, good)
                }
