"""Pause holds now: against the robot and glue simulators, through the production clients.

PAUSED is answered only once the valve reads closed and the arm stands still,
wherever in the run the pause lands; resume continues the interrupted segment
from where the arm stopped. What was sprayed is rebuilt from the robot
simulator's executed path and the glue simulator's valve log: the bead of each
planned polyline must be one continuous stroke (pieces joined within 1 mm, so
no gap) that covers it once (no piece starts behind where the last one ended,
so nothing is sprayed twice).
"""

from __future__ import annotations

import asyncio
import itertools
import math
import random
from dataclasses import dataclass

import pytest

from server.drivers.sim.glue_sim import GlueSimulator
from server.drivers.sim.robot_sim import PathSegment, RobotSimulator
from tests.rig import SPRAY_DEMO, Rig, open_rig

JOIN_MM = 1.0


@dataclass(frozen=True)
class Piece:
    """A stretch of the executed path travelled with the valve open."""

    start: tuple[float, float, float]
    end: tuple[float, float, float]

    @property
    def length(self) -> float:
        return math.dist(self.start, self.end)


def _point(segment: PathSegment, t: float) -> tuple[float, float, float]:
    """Where the arm was at wall time `t` on `segment` (the simulator moves at constant speed)."""
    span = segment.t_end - segment.t_start
    f = 0.0 if span <= 0 else min(1.0, max(0.0, (t - segment.t_start) / span))
    return tuple(a + (b - a) * f for a, b in zip(segment.start[:3], segment.end[:3], strict=True))


def _open_intervals(glue: GlueSimulator) -> list[tuple[float, float]]:
    intervals, opened = [], None
    for at, is_open in glue.valve_log:
        if is_open and opened is None:
            opened = at
        elif not is_open and opened is not None:
            intervals.append((opened, at))
            opened = None
    if opened is not None:
        intervals.append((opened, math.inf))
    return intervals


def sprayed_pieces(robot: RobotSimulator, glue: GlueSimulator) -> list[Piece]:
    """The parts of the executed path the arm travelled with the valve open, in time order."""
    pieces = []
    intervals = _open_intervals(glue)
    for segment in robot.executed_path:
        for opened, closed in intervals:
            t0, t1 = max(opened, segment.t_start), min(closed, segment.t_end)
            if t1 > t0:
                piece = Piece(_point(segment, t0), _point(segment, t1))
                if piece.length > 1e-6:
                    pieces.append(piece)
    return pieces


def beads(pieces: list[Piece]) -> list[list[Piece]]:
    """Consecutive pieces joined end to start within JOIN_MM, as one bead each."""
    strokes: list[list[Piece]] = []
    for piece in pieces:
        if strokes and math.dist(strokes[-1][-1].end, piece.start) <= JOIN_MM:
            strokes[-1].append(piece)
        else:
            strokes.append([piece])
    return strokes


def planned_polylines(plan: dict) -> list[list[tuple[float, float, float]]]:
    """Each spraying stretch of the plan: the pose before it, then its spraying waypoints."""
    lines: list[list[tuple[float, float, float]]] = []
    previous = None
    for waypoint in plan["planned_path"]:
        pose = tuple(waypoint["pose"][:3])
        if waypoint["spray"]:
            if not lines or lines[-1][-1] != previous:
                lines.append([previous])
            lines[-1].append(pose)
        previous = pose
    return lines


def assert_bead_continuous(rig: Rig, plan: dict) -> None:
    """One continuous stroke per planned polyline, covering it once."""
    strokes = beads(sprayed_pieces(rig.robot, rig.glue))
    lines = planned_polylines(plan)
    assert len(strokes) == len(lines), (
        f"{len(strokes)} separate beads for {len(lines)} polylines: a gap or a piece "
        f"sprayed twice: {[[(p.start, p.end) for p in s] for s in strokes]}"
    )
    for stroke, line in zip(strokes, lines, strict=True):
        assert math.dist(stroke[0].start, line[0]) <= JOIN_MM, (stroke[0], line[0])
        assert math.dist(stroke[-1].end, line[-1]) <= JOIN_MM, (stroke[-1], line[-1])
        planned = sum(math.dist(a, b) for a, b in itertools.pairwise(line))
        sprayed = sum(piece.length for piece in stroke)
        assert sprayed == pytest.approx(planned, abs=JOIN_MM), "a stretch sprayed twice"


async def pause_now(rig: Rig) -> dict | None:
    """POST /pause; the state as answered, checked against the devices, or None when the
    run had already ended (nothing to pause)."""
    response = await rig.api.post("/pause")
    if response.status_code == 409:
        state = await rig.state()
        assert state["state"] == "IDLE", (response.json(), state["stop_reason"])
        return None
    assert response.status_code == 202, response.json()
    answered = response.json()
    # PAUSED was entered only once both devices confirmed: valve closed, arm still.
    assert answered["state"] == "PAUSED"
    assert rig.glue.valve_open is False
    assert rig.robot.is_moving is False
    return answered


async def test_pause_mid_segment_stops_the_arm_with_the_valve_closed_and_resume_continues(
    tmp_path,
) -> None:
    async with open_rig(tmp_path) as rig:
        rig.robot.clear_path()
        await rig.start_spraying()
        async with asyncio.timeout(10):  # well inside a spraying move
            while not rig.robot.is_moving:
                await asyncio.sleep(0.002)
        assert rig.glue.valve_open
        assert await pause_now(rig) is not None
        stopped = rig.robot.position
        last = rig.robot.executed_path[-1]
        assert last.interrupted, "the segment under way was stopped where the arm was"
        await asyncio.sleep(0.2)  # held: nothing moves, nothing flows
        assert rig.robot.position == stopped and not rig.glue.valve_open
        assert (await rig.api.post("/resume")).status_code == 202
        final = await rig.wait_state("IDLE")
        assert final["stop_reason"] is None and final["operation_result"]["waypoints"] > 0
        plan = (await rig.api.get("/trajectory")).json()
        assert_bead_continuous(rig, plan)


async def test_fifty_pauses_at_random_moments_hold_at_once_and_leave_one_bead(tmp_path) -> None:
    rng = random.Random(20261123)
    pauses = 0
    async with asyncio.timeout(240), open_rig(tmp_path) as rig:
        while pauses < 50:
            rig.robot.clear_path()
            rig.glue.valve_log.clear()
            assert (await rig.api.post("/start", json=SPRAY_DEMO)).status_code == 202
            while True:
                await asyncio.sleep(rng.uniform(0.0, 0.15))
                if await pause_now(rig) is None:
                    break
                pauses += 1
                await asyncio.sleep(rng.uniform(0.0, 0.02))
                resumed = await rig.api.post("/resume")
                if resumed.status_code == 409 and resumed.json()["state"] == "IDLE":
                    break  # the pause came as the run ended: it completed while held
                assert resumed.status_code == 202, resumed.json()
            await rig.wait_state("IDLE")
            snapshot = await rig.state()
            assert snapshot["stop_reason"] is None, snapshot
            assert_bead_continuous(rig, (await rig.api.get("/trajectory")).json())
