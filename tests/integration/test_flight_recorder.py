"""The flight recorder through the whole server: a spray run on the simulated cell is
journaled sample by sample, and GET /runs/{run_id}/recording replays what the robot and
glue simulators themselves logged (their own state, not the server's) within one sample
period."""

from __future__ import annotations

import asyncio
import csv
import io
import math
from collections.abc import Sequence

import pytest

from server.drivers.sim.robot_sim import PathSegment
from tests.rig import SPRAY_DEMO, WAIT_S, Rig, open_rig


def robot_pose_at(path: Sequence[PathSegment], t: float) -> tuple[float, float, float] | None:
    """Where the robot simulator's own log puts the tool point at Unix time `t`."""
    before = None
    for segment in path:
        if segment.t_start <= t <= segment.t_end:
            span = segment.t_end - segment.t_start
            f = 0.0 if span <= 0 else (t - segment.t_start) / span
            ends = zip(segment.start[:3], segment.end[:3], strict=True)
            return tuple(a + (b - a) * f for a, b in ends)  # type: ignore[return-value]
        if segment.t_end < t:
            before = segment
    return None if before is None else tuple(before.end[:3])  # type: ignore[return-value]


def valve_states_between(log: Sequence[tuple[float, bool]], a: float, b: float) -> set[bool]:
    """The valve states the glue simulator's own log shows at some time in [a, b]."""
    state = False  # the simulator starts closed
    for at, open_ in log:
        if at > a:
            break
        state = open_
    states = {state}
    states.update(open_ for at, open_ in log if a < at <= b)
    return states


def open_intervals(log: Sequence[tuple[float, bool]]) -> list[tuple[float, float]]:
    intervals, opened = [], None
    for at, open_ in log:
        if open_ and opened is None:
            opened = at
        elif not open_ and opened is not None:
            intervals.append((opened, at))
            opened = None
    return intervals


async def recorded_run(rig: Rig) -> tuple[str, dict]:
    rig.robot.clear_path()
    started = await rig.api.post("/start", json=SPRAY_DEMO)
    assert started.status_code == 202, started.text
    run_id = started.json()["run_id"]
    snapshot = await rig.wait_state("IDLE")
    assert snapshot["operation_result"] is not None
    response = await rig.api.get(f"/runs/{run_id}/recording")
    assert response.status_code == 200, response.text
    return run_id, response.json()


async def test_a_recording_replays_what_the_simulators_logged(tmp_path) -> None:
    async with open_rig(tmp_path) as rig:
        run_id, recording = await recorded_run(rig)
        settings = rig.cell.settings
        samples = recording["samples"]
        assert recording["run"]["outcome"] == "completed"
        assert recording["sample_period_s"] == settings.device_push_interval
        assert recording["inspection"]["verdict"] in ("good", "defective")
        assert recording["stop_reason"] is None
        assert len(samples) > 10
        times = [s["time"] for s in samples]
        assert times == sorted(times)
        assert recording["run"]["started_at"] <= times[0] <= times[-1]

        # The valve: each sample's state is one the dispenser was in within a period of
        # when it reported it (the dispenser is polled every glue_poll_interval).
        period = max(settings.device_push_interval, settings.glue_poll_interval)
        log = list(rig.glue.valve_log)
        for sample in samples:
            at = sample["glue_at"]
            assert at is not None
            assert sample["valve_open"] in valve_states_between(log, at - period, at + period)
        # ...and every time glue flowed for longer than two periods, the recording saw it.
        opened = [s["glue_at"] for s in samples if s["valve_open"]]
        spans = [
            (a, b)
            for a, b in open_intervals(log)
            if times[0] <= a and b <= times[-1] and b - a > 2 * period
        ]
        assert spans, "the run opened the valve"
        for a, b in spans:
            assert any(a <= t <= b + period for t in opened), (a, b)

        # The pose: each one is where the robot simulator's executed path had the tool
        # within a sample period of when the robot reported it.
        path = rig.robot.executed_path
        posed = [s for s in samples if s["pose_at"] is not None]
        assert len(posed) > 10
        step = settings.device_push_interval
        for sample in posed:
            got = (sample["x_mm"], sample["y_mm"], sample["z_mm"])
            near = min(
                math.dist(got, pose)
                # 0.5 ms apart: the rig's arm travels at 1 m/s (250 mm/s, 4x), so a pose is
                # at most 0.25 mm from one of them; 5 ms apart missed by up to 2.5 mm
                for k in range(-200, 201)
                if (pose := robot_pose_at(path, sample["pose_at"] + step * k / 200)) is not None
            )
            assert near < 0.5, (sample, near)
        # The speed: the robot was seen moving, never faster than the fastest segment.
        fastest = max(segment.speed for segment in path) * rig.robot.speed_factor
        speeds = [s["speed_mm_s"] for s in posed if s["speed_mm_s"] is not None]
        assert speeds and max(speeds) > 0
        assert max(speeds) <= fastest * 1.05

        # The same samples as CSV, by the query parameter and by the Accept header.
        for kwargs in ({"params": {"format": "csv"}}, {"headers": {"Accept": "text/csv"}}):
            response = await rig.api.get(f"/runs/{run_id}/recording", **kwargs)
            assert response.status_code == 200
            assert response.headers["content-type"].startswith("text/csv")
            rows = list(csv.DictReader(io.StringIO(response.text)))
            assert len(rows) == len(samples)
            assert [float(r["time"]) for r in rows] == times
            assert [r["valve_open"] == "1" for r in rows] == [s["valve_open"] for s in samples]


async def test_an_unknown_run_is_a_404_and_recording_off_journals_nothing(tmp_path) -> None:
    async with open_rig(tmp_path, run_recording=False) as rig:
        response = await rig.api.get("/runs/no-such-run/recording")
        assert response.status_code == 404
        _, recording = await recorded_run(rig)
        assert recording["samples"] == [] and recording["recorded"] is False
        assert recording["run"]["outcome"] == "completed"


@pytest.mark.parametrize("role_path", ["/runs/x/recording"])
async def test_the_recording_needs_a_token(tmp_path, role_path: str) -> None:
    async with open_rig(tmp_path) as rig:
        response = await rig.api.get(role_path, headers={"Authorization": ""})
        assert response.status_code == 401


async def test_a_run_stopped_mid_spray_names_its_stop_and_its_recording_ends_there(
    tmp_path,
) -> None:
    async with open_rig(tmp_path) as rig:
        started = await rig.api.post("/start", json=SPRAY_DEMO)
        assert started.status_code == 202
        run_id = started.json()["run_id"]
        async with asyncio.timeout(WAIT_S):
            while not rig.glue.valve_open:
                await asyncio.sleep(0.005)
        await asyncio.sleep(0.3)  # a few samples with glue flowing
        assert (await rig.api.post("/estop", json={"reason": "test"})).status_code == 202
        await rig.wait_state("ERROR")
        recording = (await rig.api.get(f"/runs/{run_id}/recording")).json()
        assert recording["stop_reason"]["code"] == "EMERGENCY_STOP"
        assert recording["run"]["outcome"] != "completed"
        assert recording["inspection"] is None
        samples = recording["samples"]
        assert any(s["valve_open"] for s in samples)
        assert samples[-1]["time"] <= recording["run"]["ended_at"] + 1.0
