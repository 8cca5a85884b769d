"""Where a part's verdict shows to the plant: /kpis, /metrics, OPC UA (asyncua's own
Client) and MQTT (Debian's mosquitto), against the real server with the robot and glue
simulators.

A real run is inspected (server/quality/) and counted as its own verdict says, on every
surface alike. The counting of more parts is then shown with records built to the inspection's
contract (result["inspection"]): an inspected run's rows appended to the real journal
(what /kpis and PackML's Admin read), and an inspected run's end told to the cell's
run-ended listeners (where the metrics, the MQTT link and the webhooks hear a run end).
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client

from server.core.worker.runs import RunEnded
from server.opcua.address_space import NAMESPACE_URI
from tests.mosquitto import mosquitto, subscriber
from tests.rig import SPRAY_DEMO, WAIT_S, Rig, append_inspected_run, open_rig
from tests.serving import free_port

CELL = "cell-q"
BASE = f"glue/{CELL}"
GAP = "segment 3: a gap of 14.2 mm without bead (at most 3.0 mm)"


def summary(verdict: str, reasons: list[str], p95: float) -> dict[str, Any]:
    """An inspection summary as the contract writes it into a run's result."""
    return {
        "verdict": verdict,
        "reasons": reasons,
        "precision_mean_mm": p95 / 2,
        "precision_p95_mm": p95,
        "dispensing_cv_percent": 3.0,
        "glue_ml": 1.5,
        "vision_residual_mm": 0.2,
        "image": True,
    }


def tell_run_ended(rig: Rig, run_id: str, inspection: dict[str, Any]) -> None:
    """An inspected run's end, told to the listeners a real run's end is told to."""
    assert rig.cell.worker is not None
    result = {"workpieces": ["demo"], "waypoints": 9, "inspection": inspection}
    ended = RunEnded(
        run_id, "trajectory", "completed", 2.0, "EXECUTING_TRAJECTORY", result, None, 1
    )
    for listener in rig.cell.worker.runs.listeners:
        listener(ended)


def metric(text: str, series: str) -> float:
    """The value of one exposed series (`name{labels}`) in Prometheus text."""
    for line in text.splitlines():
        if line.startswith(series + " "):
            return float(line.split()[-1])
    raise AssertionError(f"{series} not exposed")


async def opcua_counts(port: int) -> tuple[int, int]:
    async with Client(f"opc.tcp://127.0.0.1:{port}", timeout=WAIT_S) as opc:
        await opc.load_data_type_definitions()  # the counts are PackMLCountDataType
        ns = await opc.get_namespace_index(NAMESPACE_URI)
        processed = opc.get_node(f"ns={ns};s={CELL}.Admin.ProdProcessedCount")
        defective = opc.get_node(f"ns={ns};s={CELL}.Admin.ProdDefectiveCount")
        (processed_count,) = await processed.read_value()
        (defective_count,) = await defective.read_value()
        return processed_count.Count, defective_count.Count


async def until_counts(port: int, expected: tuple[int, int]) -> None:
    """Admin is refreshed every opcua_admin_interval: wait for the counts to get there."""
    async with asyncio.timeout(WAIT_S):
        while await opcua_counts(port) != expected:
            await asyncio.sleep(0.2)


async def test_verdicts_on_kpis_metrics_packml_and_mqtt(tmp_path: Path) -> None:
    opcua_port = free_port()
    with mosquitto(tmp_path / "broker") as broker:
        overrides = {
            "cell_id": CELL,
            **broker.cell_login,
            "opcua_endpoint": f"opc.tcp://127.0.0.1:{opcua_port}",
            "opcua_admin_interval": 1,
        }
        async with (
            open_rig(tmp_path / "data", **overrides) as rig,
            subscriber(broker.port, f"{BASE}/#") as plant,
        ):
            # A real run: sprayed and inspected; every surface counts it by its verdict.
            started = await rig.api.post("/start", json=SPRAY_DEMO)
            assert started.status_code == 202, started.text
            await rig.wait_state("EXECUTING_TRAJECTORY")
            await rig.wait_state("IDLE")
            run_id = started.json()["run_id"]
            inspection = (await rig.api.get(f"/runs/{run_id}/inspection")).json()
            verdict, reasons = inspection["verdict"], inspection["reasons"]
            good, defective = int(verdict == "good"), int(verdict == "defective")
            kpis = (await rig.api.get("/kpis")).json()
            assert kpis["workpieces_processed"] == 1
            quality = kpis["quality"]
            assert (quality["parts_good"], quality["parts_defective"]) == (good, defective)
            assert quality["vision_residual_mm"] == inspection["vision"]["residual_mean_mm"]
            assert kpis["oee"]["quality"] == good
            text = (await rig.api.get("/metrics")).text
            assert metric(text, 'glue_cell_parts_inspected_total{verdict="good"}') == good
            assert metric(text, 'glue_cell_parts_inspected_total{verdict="defective"}') == defective
            assert metric(text, "glue_cell_part_trajectory_precision_mm_count") == 1
            await until_counts(opcua_port, (1, defective))
            # MQTT: the run's message with its verdict, then the cell leaving its state.
            [real] = await plant.wait(lambda: plant.on(f"{BASE}/run"))
            assert real["operation"] == "trajectory" and real["outcome"] == "completed"
            assert (real["run_id"], real["verdict"], real["reasons"]) == (run_id, verdict, reasons)
            assert real["inspection"]["verdict"] == verdict
            await plant.wait(lambda: any(e["to"] == "IDLE" for e in plant.on(f"{BASE}/event")))
            topics = [str(m.topic) for m in plant.messages]
            to_idle = [i for i, t in enumerate(topics) if t == f"{BASE}/event"][-1]
            assert topics.index(f"{BASE}/run") < to_idle

            # Inspected runs in the journal: /kpis and PackML count them.
            await append_inspected_run(rig, "good-1", summary("good", [], 0.4))
            await append_inspected_run(rig, "bad-1", summary("defective", [GAP], 1.2))
            kpis = (await rig.api.get("/kpis")).json()
            assert kpis["quality"]["parts_good"] == 1 + good
            assert kpis["quality"]["parts_defective"] == 1 + defective
            real_mean = real["inspection"]["precision_mean_mm"]
            real_p95 = real["inspection"]["precision_p95_mm"]
            assert kpis["quality"]["trajectory_precision_mm"] == {
                "mean": pytest.approx((real_mean + 0.2 + 0.6) / 3, abs=1e-3),
                "p95": pytest.approx(max(real_p95, 1.2)),
            }
            assert kpis["oee"]["quality"] == pytest.approx((1 + good) / 3)
            await until_counts(opcua_port, (3, 1 + defective))

            # An inspected run's end: the counters and the MQTT run message.
            tell_run_ended(rig, "bad-2", summary("defective", [GAP], 2.5))
            tell_run_ended(rig, "good-2", summary("good", [], 0.3))
            text = (await rig.api.get("/metrics")).text
            assert metric(text, 'glue_cell_parts_inspected_total{verdict="good"}') == 1 + good
            assert (
                metric(text, 'glue_cell_parts_inspected_total{verdict="defective"}')
                == 1 + defective
            )
            assert metric(text, "glue_cell_part_trajectory_precision_mm_count") == 3
            assert metric(text, "glue_cell_part_trajectory_precision_mm_sum") == pytest.approx(
                real_p95 + 2.8
            )
            told = await plant.wait(lambda: (r := plant.on(f"{BASE}/run")) and len(r) >= 3 and r)
            assert [(r["run_id"], r["verdict"], r["reasons"]) for r in told[1:]] == [
                ("bad-2", "defective", [GAP]),
                ("good-2", "good", []),
            ]
            assert told[1]["inspection"]["precision_p95_mm"] == 2.5
            assert all(r["cell_id"] == CELL for r in told)
