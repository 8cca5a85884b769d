"""A nozzle clogging over sprayed parts is warned of before the first bad part.

The whole path as a cell runs it: each part is a real start of the demo part on the
simulated cell, whose dispenser passes 1 % less glue with each part once the clog begins
(`GlueSimulator.clog_nozzle`). The cell measures the flow through Modbus, inspects the
bead in the rendered frame and judges the part. The first bad part is one judged
defective (its flow out of dispensing_flow_tolerance_percent, 10 %, or its glue volume
out of glue_volume_tolerance_percent) or one whose run the glue supervision stops. The
trend watch charts the figures and raises a drift warning (WebSocket `alert`, the
journal's warnings) before it. tests/integration/test_quality_trends.py checks the
rule's wording and its charts on recorded parts.
"""

from __future__ import annotations

import asyncio
import json
from typing import Any

from websockets.asyncio.client import connect

from tests.rig import SPRAY_DEMO, WAIT_S, open_rig

STEADY_PARTS = 10  # trend_min_parts (8) good parts and two more
PARTS = 30  # the clog reaches 20 % at the last; the test ends at the first bad part
CLOG_PER_PART = 0.01  # the nozzle passes 1 % less glue with each part once it clogs


def passing(index: int) -> float:
    """The share of its setpoint the nozzle passes while part `index` is sprayed."""
    return 1.0 - CLOG_PER_PART * max(0, index - STEADY_PARTS + 1)


async def test_a_nozzle_clogging_over_sprayed_parts_is_warned_of_before_a_defect(
    tmp_path,
) -> None:
    # The arm at its real speed: on the rig's 4x arm a run stretched by a busy machine
    # varies its glue far more than a clog's percent a part (one part read 226 %).
    async with open_rig(tmp_path, robot_speed_factor=1) as rig:
        url = str(rig.api.base_url).replace("http", "ws", 1) + "/ws?types=alert"
        headers = {"Authorization": rig.api.headers["authorization"]}
        runs: list[str] = []
        verdicts: list[str] = []
        glue: list[float] = []
        drifts: list[dict[str, Any]] = []
        async with connect(url, additional_headers=headers) as ws:
            await ws.recv()  # the snapshot

            async def alerts() -> None:
                async for raw in ws:
                    message = json.loads(raw)
                    data = message.get("data", message)
                    if message.get("type") == "alert" and data["code"].startswith("QUALITY_DRIFT"):
                        drifts.append(data)

            listening = asyncio.create_task(alerts())
            try:
                for index in range(PARTS):
                    rig.glue.clog_nozzle(passing(index))
                    started = await rig.api.post("/start", json=SPRAY_DEMO)
                    assert started.status_code == 202, started.text
                    runs.append(started.json()["run_id"])
                    async with asyncio.timeout(WAIT_S):
                        while (await rig.state())["state"] not in ("IDLE", "ERROR"):
                            await asyncio.sleep(0.02)
                    final = await rig.state()
                    if final["state"] == "ERROR":  # the glue supervision stopped the run
                        verdicts.append(f"stopped: {final.get('stop_reason')}")
                        glue.append(0.0)
                        break
                    assert rig.cell.journal is not None
                    await rig.cell.journal.caught_up()
                    rows = rig.cell.journal.query(
                        "inspections", filters={"run_id": runs[-1]}, limit=1
                    )
                    document = json.loads(rows[0]["document"])
                    verdicts.append(document["verdict"])
                    glue.append(document["dispensing"]["glue_ratio_percent"])
                    if document["verdict"] != "good":
                        break
            finally:
                listening.cancel()
    told = f"verdicts {verdicts}, glue % {glue}, drifts {[d['message'] for d in drifts]}"
    assert verdicts[:STEADY_PARTS] == ["good"] * STEADY_PARTS, told
    # the clog does make a bad part: judged defective, or stopped by the glue supervision
    bad = [i for i, verdict in enumerate(verdicts) if verdict != "good"]
    assert bad, told
    assert drifts, told
    warned = [
        (next(i for i, run in enumerate(runs) if f"part of run {run})" in d["message"]), d)
        for d in drifts
    ]
    first_drift, drift = min(warned, key=lambda pair: pair[0])
    assert first_drift < bad[0], told
    assert "drifting down" in drift["message"] and "nozzle" in drift["message"], told
