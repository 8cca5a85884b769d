"""Right after POST /start, what a script reads is the new run's, never the last one's.

The 202 names the run it started; GET /trajectory shows that run (not yet planned)
rather than the previous plan marked as running; GET /camera/frame?run_id= answers
409 with Retry-After until that run has captured its frame, and 404 for a run whose
frame is no longer kept, so `curl -f --retry` and scripts can tell "wait" from
"never". The camera is held (a stall injected) so "before the capture" is a fact of
the test, not a race.
"""

from __future__ import annotations

import asyncio

from tests.rig import SPRAY_DEMO, WAIT_S, open_rig, run


async def test_start_answers_its_run_and_the_views_follow_it(tmp_path) -> None:
    async with open_rig(tmp_path) as rig:
        done = await run(rig, "start")
        assert done["state"] == "IDLE", done["error"]
        first = (await rig.api.get("/trajectory")).json()
        assert first["running"] is False and first["planned"] is True

        rig.camera.inject_fault("stall")  # the next capture waits until cleared
        try:
            started = await rig.api.post("/start")
            assert started.status_code == 202, started.text
            run_id = started.json()["run_id"]
            own = {"run_id": run_id}
            assert run_id and run_id != first["run_id"]

            trajectory = (await rig.api.get("/trajectory")).json()
            assert trajectory["run_id"] == run_id
            assert trajectory["running"] is True
            assert trajectory["planned"] is False and trajectory["planned_path"] == []

            pending = await rig.api.get("/camera/frame", params=own)
            assert pending.status_code == 409, pending.text
            assert pending.headers["retry-after"] == "1"
            assert pending.json()["run_id"] == run_id
            assert pending.json()["retry_after"] == 1
            assert "not captured" in pending.json()["detail"]
            # The previous run's frame is still the latest, and says whose it is.
            latest = await rig.api.get("/camera/frame")
            assert latest.status_code == 200
            assert latest.headers["x-frame-run-id"] == first["run_id"]
        finally:
            rig.camera.clear_faults()

        async with asyncio.timeout(WAIT_S):
            while (frame := await rig.api.get("/camera/frame", params=own)).status_code != 200:
                assert frame.status_code == 409, frame.text
                await asyncio.sleep(0.02)
        assert frame.headers["x-frame-run-id"] == run_id
        await rig.wait_state("IDLE")
        planned = (await rig.api.get("/trajectory")).json()
        assert planned["run_id"] == run_id and planned["planned"] is True
        assert planned["running"] is False and planned["planned_path"]

        gone = await rig.api.get("/camera/frame", params={"run_id": first["run_id"]})
        assert gone.status_code == 404 and "retry-after" not in gone.headers
        assert first["run_id"] in gone.json()["detail"]
        assert run_id in gone.json()["detail"]  # whose frame is kept instead


async def test_a_run_of_another_kind_is_not_shown_as_the_trajectory_running(tmp_path) -> None:
    async with open_rig(tmp_path) as rig:
        done = await run(rig, "start", SPRAY_DEMO)
        assert done["state"] == "IDLE", done["error"]
        rig.camera.inject_fault("stall")  # robot calibration waits on the camera
        try:
            started = await rig.api.post("/calibrate-robot")
            assert started.status_code == 202, started.text
            assert started.json()["run_id"]
            trajectory = (await rig.api.get("/trajectory")).json()
            assert trajectory["running"] is False  # the last trajectory run is over
        finally:
            rig.camera.clear_faults()
        await rig.wait_state("IDLE")
        home = await rig.api.post("/home")
        assert home.status_code == 202 and home.json()["run_id"] is None  # no run started
