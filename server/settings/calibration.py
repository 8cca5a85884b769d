"""The `CalibrationSettings` section of the settings. The table's markers and the
chessboard, and how good a calibration must be.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import ClassVar
from urllib.parse import urlsplit

from pydantic import Field, field_validator

from server.settings.motion import Millimetres
from server.settings.section import Section

# Robot positions (mm, robot base frame, on the table plane z=0) of ArUco markers 0-8.
DEFAULT_MARKER_POSITIONS_MM: list[tuple[float, float]] = [
    (x, y) for y in (-150.0, 0.0, 150.0) for x in (250.0, 400.0, 550.0)
]


def outside_workspace(
    point: Sequence[float], low: Sequence[float], high: Sequence[float]
) -> str | None:
    """Which axis of `point` (x, y, z mm; more is ignored) leaves [low, high], or None."""
    for axis, value, lo, hi in zip("xyz", point[:3], low, high, strict=True):
        if not lo <= value <= hi:
            return f"{axis}={value:.1f} mm, allowed {lo:.0f}..{hi:.0f} mm"
    return None


def parse_tcp_address(value: str) -> tuple[str, int]:
    """`tcp://host:port` → (host, port); ValueError naming the setting otherwise."""
    parts = urlsplit(value)
    try:
        port = parts.port
    except ValueError:  # past 65535
        port = None
    if parts.scheme != "tcp" or not parts.hostname or not port:
        raise ValueError(f"GLUE_CONTROLLER_PORT={value!r}: expected tcp://host:port")
    return parts.hostname, port


def marker_layout_problems(
    positions: Sequence[Sequence[float]],
    workspace_min: Sequence[float],
    workspace_max: Sequence[float],
    marker_size: float,
) -> list[str]:
    """Every way a marker layout fails (`Settings._marker_layout` says why each rule), each
    naming its markers: a taught draft is corrected in one pass, not one marker a try."""
    points = [(float(x), float(y)) for x, y in positions]
    (x_low, y_low, *_), (x_high, y_high, *_) = workspace_min, workspace_max
    problems = [
        f"marker {i} at ({x:g}, {y:g}) mm is outside the workspace (workspace_min_mm/"
        f"workspace_max_mm: x {x_low:g}..{x_high:g}, y {y_low:g}..{y_high:g} mm)"
        for i, (x, y) in enumerate(points)
        if not (x_low <= x <= x_high and y_low <= y <= y_high)
    ]
    diagonal = marker_size * math.sqrt(2.0)
    problems += [
        f"markers {i} and {j} are {math.dist(p, q):.1f} mm apart, less than a marker's "
        f"diagonal ({diagonal:.1f} mm for marker_size_mm={marker_size:g}): they would overlap"
        for (i, p), (j, q) in itertools.combinations(enumerate(points), 2)
        if math.dist(p, q) < diagonal
    ]
    for left_out in range(len(points)):
        rest = [p for i, p in enumerate(points) if i != left_out]
        if not _has_four_in_general_position(rest, marker_size):
            problems.append(
                f"the layout is degenerate: a calibration needs four markers no three of which "
                f"lie on one line (within marker_size_mm={marker_size:g} mm), also with any "
                f"one marker left out; without marker {left_out} there are not"
            )
            break
    return problems


def _has_four_in_general_position(points: list[tuple[float, float]], tolerance: float) -> bool:
    """Whether four of the points have no three within `tolerance` of one line."""

    def apart(a: tuple[float, float], b: tuple[float, float], c: tuple[float, float]) -> bool:
        cross = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        longest = max(math.dist(a, b), math.dist(b, c), math.dist(a, c))
        return longest > 0 and abs(cross) / longest > tolerance  # the triangle's least height

    return any(
        all(apart(*three) for three in itertools.combinations(four, 3))
        for four in itertools.combinations(points, 4)
    )


class CalibrationSettings(Section):
    """The table's markers and the chessboard, and how good a calibration must be."""

    title: ClassVar[str] = "Calibration"

    marker_positions_mm: list[tuple[Millimetres, Millimetres]] = Field(
        default_factory=lambda: list(DEFAULT_MARKER_POSITIONS_MM),
        description="robot (x, y) mm on the table of the centres of ArUco markers 0-8; "
        "the default is the simulated table's grid, so a real camera needs it set",
    )
    marker_size_mm: float = Field(
        30.0,
        ge=1,
        le=500,
        description="side of each marker's black square as printed (measure it): the "
        "robot calibration checks its map's scale against it",
    )
    calibration_max_error_mm: float = Field(
        1.0, ge=0.01, le=20, description="robot calibration fails above this mean marker error (mm)"
    )
    calibration_max_scale_error_pct: float = Field(
        1.0,
        ge=0.01,
        le=10,
        description="robot calibration fails when the markers' side through its map differs "
        "from marker_size_mm by more than this (%)",
    )
    calibration_max_holdout_error_mm: float = Field(
        1.0,
        ge=0.01,
        le=20,
        description="robot calibration fails when a map fitted without one marker misses "
        "that marker by more than this (leave-one-out, worst marker)",
    )
    chessboard_cols: int = Field(9, ge=3, le=40, description="inner corners per row")
    chessboard_rows: int = Field(6, ge=3, le=40, description="inner corners per column")
    chessboard_square_mm: float = Field(
        30.0, ge=1, le=500, description="side of one chessboard square as printed"
    )
    camera_calibration_views: int = Field(
        10, ge=5, le=100, description="chessboard views a camera calibration takes"
    )
    camera_calibration_view_interval_s: float | None = Field(
        None,
        ge=0,
        le=60,
        description="pause between chessboard captures, for a person to move the board; "
        "default 2 s on a real camera, 0 on the simulator (it shows its own views)",
    )

    @field_validator("marker_positions_mm")
    @classmethod
    def _nine_markers(cls, value: list[tuple[float, float]]) -> list[tuple[float, float]]:
        if len(value) != 9:
            raise ValueError("marker_positions_mm needs the robot positions of markers 0-8 (nine)")
        return value
