"""A part paused and resumed is judged on the glue its path needs, once, on the served cell.

The demo part is sprayed at the dashboard test's slow bead speed (30 mm/s: time to watch
a run), once clean and once paused mid-bead, held a few seconds, and resumed. Both parts
must be judged `good`: the glue measured within glue_volume_tolerance_percent of the glue
the plan needs, that need the same for both (the path's glue, counted once), and the
simulated dispenser's own integral of what left the nozzle agreeing with it.

Run on the simulators as the tests run them (the arm four times faster than its
commanded speed, the dispenser's dynamics at their own pace) and as the served simulated
cell runs them (both at `simulation_speed_factor`): a speed-following dispenser follows
the arm's actual speed, however fast the simulated arm is made to move.
"""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from tests.rig import SPRAY_DEMO, WAIT_S, Rig, open_rig

SLOW_SPRAY_MM_S = 30.0
HELD_S = 3.0  # in PAUSED: longer than the dispenser's fixed-flow threshold (1 s)


async def spray_slowly(rig: Rig) -> None:
    demo = (await rig.api.get("/workpieces/demo")).json()
    body = {
        "name": demo["name"],
        "outline_mm": demo["outline_mm"],
        "spray": {**demo["spray"], "speed_mm_s": SLOW_SPRAY_MM_S},
    }
    assert (await rig.api.put("/workpieces/demo", json=body)).status_code == 200


async def spray_demo(rig: Rig, *, pause: bool) -> dict[str, Any]:
    """Spray the demo part (paused mid-bead and resumed when `pause`); its inspection."""
    before = rig.glue.dispensed_ml
    started = await rig.api.post("/start", json=SPRAY_DEMO)
    assert started.status_code == 202, started.text
    run_id = started.json()["run_id"]
    if pause:
        async with asyncio.timeout(WAIT_S):  # the arm drawing a bead with glue flowing
            while not (rig.glue.valve_open and rig.robot.is_moving):
                await asyncio.sleep(0.002)
        await asyncio.sleep(0.1)
        paused = await rig.api.post("/pause")
        assert paused.status_code == 202, paused.json()
        assert paused.json()["state"] == "PAUSED"
        await asyncio.sleep(HELD_S)
        assert (await rig.state())["state"] == "PAUSED"
        assert (await rig.api.post("/resume")).status_code == 202
    final = await rig.wait_state("IDLE")
    assert final["stop_reason"] is None, final
    response = await rig.api.get(f"/runs/{run_id}/inspection")
    assert response.status_code == 200, response.text
    document: dict[str, Any] = response.json()
    document["simulator_ml"] = rig.glue.dispensed_ml - before
    return document


@pytest.mark.parametrize(
    ("robot_factor", "glue_factor"),
    [(4.0, 1.0), (4.0, 4.0)],
    ids=["test-rig-speeds", "simulation-speed-factor"],
)
async def test_a_paused_and_resumed_part_needs_and_gets_the_glue_of_its_path_once(
    tmp_path, robot_factor: float, glue_factor: float
) -> None:
    async with open_rig(
        tmp_path, robot_speed_factor=robot_factor, glue_speed_factor=glue_factor
    ) as rig:
        await spray_slowly(rig)
        clean = await spray_demo(rig, pause=False)
        resumed = await spray_demo(rig, pause=True)
        tolerance = rig.cell.settings.glue_volume_tolerance_percent
    for name, document in (("clean", clean), ("paused and resumed", resumed)):
        dispensing = document["dispensing"]
        assert document["verdict"] == "good", (name, document["reasons"])
        assert abs(dispensing["glue_ratio_percent"] - 100.0) <= tolerance, (name, dispensing)
        # What left the nozzle, by the simulator's own integral, is what the server measured.
        assert document["simulator_ml"] == pytest.approx(dispensing["glue_ml"], abs=0.002), name
    # The resumed part needs its path's glue once, the same as the clean one.
    assert resumed["dispensing"]["expected_ml"] == pytest.approx(
        clean["dispensing"]["expected_ml"], rel=0.02
    )
