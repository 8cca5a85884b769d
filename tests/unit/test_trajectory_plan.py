"""The spray path as planned and checked before the robot moves (pure functions, no devices).

plan_path: for each polyline, travel above its start, descend, spray along it, lift; glue
flows only on the spraying segments, at spray height and the workpiece's spray speed.
check_workspace: one waypoint outside the workspace on any axis refuses the whole path,
naming the waypoint and the axis; the workspace's own boundary is inside.
"""

from __future__ import annotations

import asyncio
import itertools
import math
import threading
import time
from typing import Any

import numpy as np
import pytest

from server.common.errors import OperationError
from server.core.operations import trajectory
from server.core.operations.trajectory import (
    TRAVEL_CLEARANCE_MM,
    Waypoint,
    check_workspace,
    plan_path,
    plan_within_limit,
)
from server.core.operations.workpieces import Target
from server.drivers.base import Pose
from server.settings.model import Settings
from server.storage.workpieces import SpraySettings
from server.vision.paths import SprayPattern, spray_polylines

RECTANGLE = [(300.0, -25.0), (400.0, -25.0), (400.0, 25.0), (300.0, 25.0)]
SETTINGS = Settings(spray_height_mm=20.0, travel_speed_mm_s=250.0)
SPRAY_Z = SETTINGS.spray_height_mm
TRAVEL_Z = SPRAY_Z + TRAVEL_CLEARANCE_MM


def target(
    points: list[tuple[float, float]] = RECTANGLE,
    name: str = "part",
    x_shift: float = 0.0,
    **spray: Any,
) -> Target:
    pts = np.asarray(points, dtype=np.float64) + np.array([x_shift, 0.0])
    return Target(name, name, pts, SpraySettings(speed_mm_s=80.0, flow_rate_ml_min=25.0, **spray))


def polylines_of(t: Target) -> list[np.ndarray]:
    """What the vision module gives plan_path for this target (tested in test_vision_paths)."""
    s = t.spray
    pattern = SprayPattern(
        outline_offset_mm=s.outline_offset_mm,
        outline=s.outline,
        fill=s.fill,
        fill_spacing_mm=s.fill_spacing_mm,
        fill_angle_deg=s.fill_angle_deg,
    )
    return spray_polylines(np.asarray(t.outline_mm), pattern)


def split_runs(path: list[Waypoint]) -> list[list[Waypoint]]:
    """The path cut after each lift (a non-spraying waypoint at travel height after spraying)."""
    runs: list[list[Waypoint]] = [[]]
    for w in path:
        runs[-1].append(w)
        if not w.spray and w.pose.z == TRAVEL_Z and any(v.spray for v in runs[-1]):
            runs.append([])
    assert runs[-1] == [], "the path must end with a lift"
    return runs[:-1]


# --- plan_path -------------------------------------------------------------------------------


def test_an_outline_is_travel_above_descend_spray_lift() -> None:
    t = target()
    (line,) = polylines_of(t)
    path = plan_path([t], SETTINGS)
    assert len(path) == 1 + 1 + (len(line) - 1) + 1

    above, down, *spraying, lift = path
    x0, y0 = line[0]
    assert above == Waypoint(Pose(x0, y0, TRAVEL_Z), False, 250.0, "part")
    assert down == Waypoint(Pose(x0, y0, SPRAY_Z), False, 250.0, "part")
    assert [(w.pose.x, w.pose.y) for w in spraying] == [tuple(p) for p in line[1:]]
    for w in spraying:
        assert w.spray and w.pose.z == SPRAY_Z
        assert w.speed == 80.0 and w.flow_rate_ml_min == 25.0 and w.workpiece == "part"
    xl, yl = line[-1]
    assert lift == Waypoint(Pose(xl, yl, TRAVEL_Z), False, 250.0, "part")
    # The bead closes on itself and goes round the rectangle's corners.
    assert (spraying[-1].pose.x, spraying[-1].pose.y) == (x0, y0)
    assert {(w.pose.x, w.pose.y) for w in spraying} == set(RECTANGLE)


def test_tool_orientation_is_the_default_pose_everywhere() -> None:
    for w in plan_path([target()], SETTINGS):
        assert (w.pose.rx, w.pose.ry, w.pose.rz) == (180.0, 0.0, 0.0)


@pytest.mark.parametrize("fill", ["zigzag", "raster"])
def test_every_polyline_of_a_fill_is_entered_and_left_the_same_way(fill: str) -> None:
    t = target(fill=fill, fill_spacing_mm=10.0)
    lines = polylines_of(t)
    assert len(lines) >= 2  # the bead, then the fill
    path = plan_path([t], SETTINGS)
    runs = split_runs(path)
    assert len(runs) == len(lines)
    for run, line in zip(runs, lines, strict=True):
        above, down, *spraying, lift = run
        assert (above.pose.x, above.pose.y, above.pose.z) == (*line[0], TRAVEL_Z)
        assert (down.pose.x, down.pose.y, down.pose.z) == (*line[0], SPRAY_Z)
        assert not above.spray and not down.spray and not lift.spray
        assert len(spraying) == len(line) - 1
        assert all(w.spray for w in spraying)
        assert (lift.pose.x, lift.pose.y, lift.pose.z) == (*line[-1], TRAVEL_Z)


def test_glue_flows_only_at_spray_height_and_spray_speed() -> None:
    path = plan_path([target(fill="zigzag", fill_spacing_mm=8.0)], SETTINGS)
    for before, w in itertools.pairwise(path):
        if w.spray:
            # the whole segment that ends at a spraying waypoint lies at spray height
            assert before.pose.z == SPRAY_Z and w.pose.z == SPRAY_Z
            assert w.speed == 80.0
        else:
            assert w.speed == SETTINGS.travel_speed_mm_s
    assert not path[0].spray and not path[-1].spray
    assert path[0].pose.z == path[-1].pose.z == TRAVEL_Z


def test_workpieces_are_sprayed_one_after_the_other_with_their_own_settings() -> None:
    first = target(name="left")
    second = Target(
        "right",
        "right",
        np.asarray(RECTANGLE) + np.array([200.0, 0.0]),
        SpraySettings(speed_mm_s=40.0, flow_rate_ml_min=12.5),
    )
    path = plan_path([first, second], SETTINGS)
    names = [w.workpiece for w in path]
    assert names == sorted(names)  # all of "left", then all of "right"
    assert set(names) == {"left", "right"}
    right = [w for w in path if w.workpiece == "right" and w.spray]
    assert right and all(w.speed == 40.0 and w.flow_rate_ml_min == 12.5 for w in right)
    assert all(w.pose.x >= 500.0 for w in path if w.workpiece == "right")


def test_travel_height_follows_the_spray_height_setting() -> None:
    settings = Settings(spray_height_mm=5.0, travel_speed_mm_s=400.0)
    path = plan_path([target()], settings)
    assert {w.pose.z for w in path} == {5.0, 5.0 + TRAVEL_CLEARANCE_MM}
    assert {w.speed for w in path if not w.spray} == {400.0}


def test_a_waypoint_as_dict_is_what_the_api_shows() -> None:
    w = plan_path([target()], SETTINGS)[2]
    assert w.as_dict() == {
        "pose": [w.pose.x, w.pose.y, SPRAY_Z, 180.0, 0.0, 0.0],
        "spray": True,
        "speed": 80.0,
        "workpiece": "part",
    }


def test_no_targets_is_path_empty() -> None:
    with pytest.raises(OperationError) as caught:
        plan_path([], SETTINGS)
    assert caught.value.code == "PATH_EMPTY"


def test_spray_settings_that_spray_nothing_are_path_empty() -> None:
    with pytest.raises(OperationError) as caught:
        plan_path([target(outline=False, fill="none")], SETTINGS)
    assert caught.value.code == "PATH_EMPTY"


def test_an_outline_without_area_is_path_invalid_naming_the_workpiece() -> None:
    collinear = [(300.0, 0.0), (350.0, 0.0), (400.0, 0.0)]
    with pytest.raises(OperationError) as caught:
        plan_path([target(collinear, name="flat")], SETTINGS)
    assert caught.value.code == "PATH_INVALID"
    assert "flat" in str(caught.value)


# --- check_workspace -------------------------------------------------------------------------

LOW = SETTINGS.workspace_min_mm  # (100, -400, -5)
HIGH = SETTINGS.workspace_max_mm  # (800, 400, 500)
CENTRE = tuple((lo + hi) / 2 for lo, hi in zip(LOW, HIGH, strict=True))


def waypoint(x: float, y: float, z: float, name: str = "part", **rotation: float) -> Waypoint:
    return Waypoint(Pose(x, y, z, **rotation), False, 100.0, name)


def test_a_path_inside_the_workspace_passes() -> None:
    path = plan_path([target()], SETTINGS)
    assert check_workspace(path, SETTINGS) is None


def test_the_boundary_itself_is_inside() -> None:
    corners = [waypoint(x, y, z) for x in (LOW[0], HIGH[0]) for y in (LOW[1], HIGH[1])
               for z in (LOW[2], HIGH[2])]  # fmt: skip
    check_workspace(corners, SETTINGS)


def test_orientation_is_not_limited() -> None:
    check_workspace([waypoint(*CENTRE, rx=-180.0, ry=359.0, rz=1e4)], SETTINGS)


@pytest.mark.parametrize("axis", [0, 1, 2], ids=["x", "y", "z"])
@pytest.mark.parametrize("side", ["below", "above"])
def test_one_waypoint_just_outside_refuses_the_path_naming_it_and_the_axis(
    axis: int, side: str
) -> None:
    outside = list(CENTRE)
    outside[axis] = LOW[axis] - 0.1 if side == "below" else HIGH[axis] + 0.1
    path = [waypoint(*CENTRE, name="first")] * 2 + [waypoint(*outside, name="stray")]
    path += [waypoint(*CENTRE, name="last")] * 2
    with pytest.raises(OperationError) as caught:
        check_workspace(path, SETTINGS)
    error = caught.value
    assert error.code == "WORKSPACE_VIOLATION"
    message = str(error)
    assert "waypoint 3 of 5 (stray)" in message
    assert f"{'xyz'[axis]}={outside[axis]:.1f} mm" in message
    assert f"allowed {LOW[axis]:.0f}..{HIGH[axis]:.0f} mm" in message
    assert not error.recoverable


@pytest.mark.parametrize("axis", [0, 1, 2], ids=["x", "y", "z"])
def test_a_coordinate_that_is_not_a_number_is_refused(axis: int) -> None:
    bad = list(CENTRE)
    bad[axis] = math.nan
    with pytest.raises(OperationError) as caught:
        check_workspace([waypoint(*bad)], SETTINGS)
    assert caught.value.code == "WORKSPACE_VIOLATION"
    assert f"{'xyz'[axis]}=nan" in str(caught.value)


def test_the_first_waypoint_outside_is_the_one_named() -> None:
    path = [waypoint(*CENTRE), waypoint(HIGH[0] + 5, 0, 0), waypoint(LOW[0] - 5, 0, 0)]
    with pytest.raises(OperationError, match=r"waypoint 2 of 3 .* x=805\.0 mm"):
        check_workspace(path, SETTINGS)


def test_a_travel_height_above_the_workspace_is_refused_at_the_first_waypoint() -> None:
    settings = Settings(spray_height_mm=HIGH[2] - TRAVEL_CLEARANCE_MM + 1.0)
    path = plan_path([target()], settings)
    with pytest.raises(OperationError, match=r"waypoint 1 of \d+ \(part\) .* z=501\.0 mm"):
        check_workspace(path, settings)


def test_a_part_partly_outside_is_refused_before_anything_else() -> None:
    path = plan_path([target(x_shift=LOW[0] - 300.0 - 10.0)], SETTINGS)  # x from 90 mm
    with pytest.raises(OperationError) as caught:
        check_workspace(path, SETTINGS)
    assert caught.value.code == "WORKSPACE_VIOLATION" and "x=90.0 mm" in str(caught.value)


# --- planning bounded and stoppable ------------------------------------------------------------


def gear(points: int = 800, radius: float = 300.0) -> list[tuple[float, float]]:
    """The issue's part: an 800-point outline (teeth 15 % deep); with a 1 mm fill its plan
    takes tens of seconds here."""
    t = np.linspace(0.0, 2 * math.pi, points, endpoint=False)
    r = radius * (1 + 0.15 * np.where(np.arange(points) % 2 == 0, 1.0, -1.0))
    return [
        (450.0 + float(a * math.cos(b)), float(a * math.sin(b))) for a, b in zip(r, t, strict=True)
    ]


class _EndlessPlan:
    """A plan_path stand-in that runs until its checkpoint stops it, and says when it has."""

    def __init__(self) -> None:
        self.started = threading.Event()
        self.stopped = threading.Event()

    def __call__(self, targets: Any, settings: Settings, checkpoint: Any) -> list[Waypoint]:
        self.started.set()
        try:
            while True:
                checkpoint()
                time.sleep(0.001)
        finally:
            self.stopped.set()


async def test_a_plan_past_planning_timeout_fails_with_planning_timeout() -> None:
    settings = Settings(planning_timeout=0.05)
    heavy = target(gear(), name="gear", fill="zigzag", fill_spacing_mm=1.0)
    with pytest.raises(OperationError) as caught:
        await plan_within_limit([heavy], settings)
    assert caught.value.code == "PLANNING_TIMEOUT"
    assert "gear" in str(caught.value) and "planning_timeout" in str(caught.value)


async def test_a_timed_out_plan_has_stopped_when_the_run_hears_of_it(monkeypatch) -> None:
    endless = _EndlessPlan()
    monkeypatch.setattr(trajectory, "plan_path", endless)
    with pytest.raises(OperationError, match="planning_timeout"):
        await plan_within_limit([target()], Settings(planning_timeout=0.05))
    assert endless.stopped.is_set()


async def test_a_cancelled_plan_has_stopped_when_the_cancellation_returns(monkeypatch) -> None:
    # The run's task cancelled must not leave the planning thread running on, for minutes.
    endless = _EndlessPlan()
    monkeypatch.setattr(trajectory, "plan_path", endless)
    planning = asyncio.create_task(plan_within_limit([target()], Settings()))
    while not endless.started.is_set():
        await asyncio.sleep(0.001)
    planning.cancel()
    with pytest.raises(asyncio.CancelledError):
        await planning
    assert endless.stopped.is_set()


async def test_a_plan_within_the_limit_is_the_plan() -> None:
    parts = [target(fill="zigzag", fill_spacing_mm=8.0)]
    assert await plan_within_limit(parts, SETTINGS) == plan_path(parts, SETTINGS)


async def test_an_invalid_path_keeps_its_own_code_under_the_limit() -> None:
    flat = target([(300.0, 0.0), (350.0, 0.0), (400.0, 0.0)], name="flat")
    with pytest.raises(OperationError) as caught:
        await plan_within_limit([flat], SETTINGS)
    assert caught.value.code == "PATH_INVALID"
