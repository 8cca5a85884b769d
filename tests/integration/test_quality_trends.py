"""Quality trends before defects, on the served cell: a nozzle clogging over 30 parts
raises the drift warning (WebSocket `alert`, the journal's warnings) before the first
defective part, and GET /quality/trends charts it.

The 30 parts are recorded part rows: each part's whole inspection is built as a clogging
nozzle makes it (the flow, and with it the glue volume and the bead's width, falling a
percent a part after a steady start), judged by the cell's own verdict rules, written
through the journal's record builders, and its run's end told to the run listeners as
the worker tells them. Thirty real sprayed runs would take minutes; the drift rule sees
the same figures either way.
"""

from __future__ import annotations

import asyncio
import json
import random
import time
from collections.abc import AsyncIterator
from typing import Any

import pytest
from websockets.asyncio.client import connect

from server.core.operations.inspection import summary_of
from server.core.worker.runs import RunEnded
from server.quality.verdict import dispensing_reasons
from server.settings.quality import QualitySettings
from server.storage.journal import records
from tests.rig import Rig, open_rig

STEADY_PARTS = 12
PARTS = 30
CLOG_PER_PART = 0.01  # the nozzle passes 1 % less glue with each part once it clogs
EXPECTED_ML = 0.5
SETPOINT = 60.0
SPRAYING_S = 4.0


@pytest.fixture
async def rig(tmp_path) -> AsyncIterator[Rig]:
    async with open_rig(tmp_path) as running:
        yield running


def clogged_inspection(run_id: str, index: int, noise: random.Random) -> dict[str, Any]:
    """Part `index`'s whole inspection, its figures as a clogging nozzle leaves them."""
    passing = 1.0 - CLOG_PER_PART * max(0, index - STEADY_PARTS + 1)
    flow = SETPOINT * passing * (1 + noise.gauss(0, 0.005))
    ratio = round(100.0 * passing + noise.gauss(0, 1.0), 2)
    off = abs(flow - SETPOINT) / SETPOINT * 100
    dispensing = {
        "readings": 40,
        "flow_mean_ml_min": round(flow, 3),
        "setpoint_ml_min": SETPOINT,
        "cv_percent": round(2.0 + noise.gauss(0, 0.2), 3),
        "out_of_tolerance_s": SPRAYING_S if off > 10.0 else 0.0,
        "tolerance_percent": 10.0,
        "spraying_s": SPRAYING_S,
        "glue_ml": round(EXPECTED_ML * ratio / 100, 4),
        "expected_ml": EXPECTED_ML,
        "glue_ratio_percent": ratio,
    }
    reasons = dispensing_reasons(dispensing, QualitySettings())
    width = 3.0 * passing * (1 + noise.gauss(0, 0.01))
    return {
        "run_id": run_id,
        "verdict": "defective" if reasons else "good",
        "reasons": reasons,
        "at": time.time(),
        "took_s": 0.2,
        "precision": {"mean_mm": 0.2, "p95_mm": round(0.3 + noise.gauss(0, 0.02), 3)},
        "dispensing": dispensing,
        "vision": {"residual_mean_mm": round(0.1 + noise.gauss(0, 0.01), 3)},
        "segments": [{"index": 1, "width_mean_mm": round(width, 2), "expected_width_mm": 3.0}],
        "samples": {"poses": 100, "flows": 40, "windows": 1},
        "image": False,
    }


async def record_part(rig: Rig, run_id: str, document: dict[str, Any]) -> None:
    """The part's run and inspection on record, and its end told as the worker tells it."""
    summary = summary_of(document)
    result = {"workpieces": ["demo"], "waypoints": 9, "inspection": summary}
    now = time.time()
    journal = rig.cell.journal
    assert journal is not None
    written = journal.append(
        [
            records.operation_started(run_id, "trajectory", now - 5, {"workpiece_id": "demo"}),
            records.inspection(now, run_id, document),
            records.operation_ended(run_id, now, "completed", result, None, 1),
        ]
    )
    assert written is not None
    await written
    ended = RunEnded(run_id, "trajectory", "completed", 5.0, "SPRAYING", result, None, 1)
    for listener in rig.cell.worker.runs.listeners:  # type: ignore[union-attr]
        listener(ended)
    await asyncio.sleep(0)  # the watch judges it once the worker would have yielded


async def test_a_clogging_nozzle_is_warned_of_before_the_first_defective_part(rig: Rig) -> None:
    noise = random.Random(36)
    url = str(rig.api.base_url).replace("http", "ws", 1) + "/ws?types=alert"
    headers = {"Authorization": rig.api.headers["authorization"]}
    verdicts: list[str] = []
    runs: list[str] = []
    async with connect(url, additional_headers=headers) as ws:
        await ws.recv()  # the snapshot
        for index in range(PARTS):
            run_id = f"clog-{index:02d}"
            document = clogged_inspection(run_id, index, noise)
            await record_part(rig, run_id, document)
            verdicts.append(document["verdict"])
            runs.append(run_id)
        drifts: list[dict[str, Any]] = []
        async with asyncio.timeout(30):
            while not any(d["code"] == "QUALITY_DRIFT_GLUE_VOLUME_PERCENT" for d in drifts):
                message = json.loads(await ws.recv())
                data = message.get("data", message)
                if message.get("type") == "alert" and data["code"].startswith("QUALITY_DRIFT"):
                    drifts.append(data)
    first_defective = verdicts.index("defective")
    assert STEADY_PARTS < first_defective < PARTS  # the clog does make defective parts
    glue = next(d for d in drifts if d["code"] == "QUALITY_DRIFT_GLUE_VOLUME_PERCENT")
    warned_at = next(i for i, run in enumerate(runs) if f"part of run {run})" in glue["message"])
    assert warned_at < first_defective, (warned_at, first_defective)
    assert "glue volume is drifting down" in glue["message"]
    assert "check the nozzle for a clog" in glue["message"]
    assert glue["component"] == "quality" and glue["severity"] == "warning"
    # On record as a warning, and charted with the drift.
    rows = (
        await rig.api.get("/errors", params={"code": "QUALITY_DRIFT_GLUE_VOLUME_PERCENT"})
    ).json()["errors"]
    assert rows and rows[0]["classification"] == "warning"
    trends = (await rig.api.get("/quality/trends")).json()
    charts = {chart["figure"]: chart for chart in trends["charts"]}
    chart = charts["glue_volume_percent"]
    assert [point["run_id"] for point in chart["points"]] == runs
    assert chart["drift"]["direction"] == "down"
    assert chart["lower"] < chart["centre"] < chart["upper"]
    assert len(charts["bead_width_percent"]["points"]) == PARTS


async def test_the_charts_come_back_from_the_journal_after_a_restart(tmp_path) -> None:
    """The parts on record are charted again at start-up, without raising again the
    warnings they raised the first time."""
    noise = random.Random(36)
    runs = [f"clog-{index:02d}" for index in range(PARTS)]
    async with open_rig(tmp_path) as rig:
        for index, run_id in enumerate(runs):
            await record_part(rig, run_id, clogged_inspection(run_id, index, noise))
        before = (await rig.api.get("/quality/trends")).json()
    async with open_rig(tmp_path) as rig:
        after = (await rig.api.get("/quality/trends")).json()
        warned = (
            await rig.api.get("/errors", params={"code": "QUALITY_DRIFT_GLUE_VOLUME_PERCENT"})
        ).json()["errors"]
    assert after["parts"] == PARTS
    glue = {chart["figure"]: chart for chart in after["charts"]}["glue_volume_percent"]
    assert [point["run_id"] for point in glue["points"]] == runs
    was = {chart["figure"]: chart for chart in before["charts"]}["glue_volume_percent"]
    assert [p["value"] for p in glue["points"]] == [p["value"] for p in was["points"]]
    assert glue["drift"] == was["drift"] and glue["centre"] == was["centre"]
    assert len(warned) == 1  # the first run's warning only
