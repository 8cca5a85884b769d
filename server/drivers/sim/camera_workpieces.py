"""Workpieces for the simulated table: flat parts with known outlines and poses.

Ground truth for the workpiece finder (position within 1 mm, rotation within 1°): each
library shape is defined with its area centroid at its local origin, so a pose (x, y,
rotation) names exactly the point and angle vision should report; `symmetry_deg` says which
other angles are equally right (a rectangle turned by 180° looks the same).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

# Where the simulated cell's demo part lies (shape, x mm, y mm, rotation deg): placed by
# commissioning, and shown by the network camera simulator (camera_stream.py).
DEMO_WORKPIECE = ("rect-120x80", 400.0, -75.0, 5.0)


@dataclass(frozen=True)
class WorkpieceShape:
    """A flat part's outline in its own frame (mm, counter-clockwise, area centroid at 0, 0).

    `symmetry_deg` is the smallest turn that maps the outline onto itself (360: none, 0: any
    turn, as for a disc), so a rotation check knows which answers are equally right.
    """

    name: str
    outline_mm: tuple[tuple[float, float], ...]
    symmetry_deg: float
    description: str = ""

    @classmethod
    def from_outline(
        cls, name: str, outline: ArrayLike, symmetry_deg: float, description: str = ""
    ) -> WorkpieceShape:
        """Re-centre any simple polygon on its area centroid and orient it counter-clockwise."""
        pts = np.asarray(outline, dtype=np.float64)
        area, centroid = polygon_area_centroid(pts)
        if area < 0:
            pts = pts[::-1]
        pts = pts - centroid
        return cls(name, tuple((float(x), float(y)) for x, y in pts), symmetry_deg, description)

    @property
    def area_mm2(self) -> float:
        return abs(polygon_area_centroid(np.asarray(self.outline_mm))[0])


def polygon_area_centroid(points: ArrayLike) -> tuple[float, NDArray[np.float64]]:
    """Signed area (positive counter-clockwise) and area centroid of a simple polygon (shoelace)."""
    pts = np.asarray(points, dtype=np.float64)
    x, y = pts[:, 0], pts[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = cross.sum() / 2.0
    centroid = np.array([((x + xn) * cross).sum(), ((y + yn) * cross).sum()]) / (6.0 * area)
    return float(area), centroid


def _rounded_rect(width: float, height: float, radius: float, segments: int = 12) -> NDArray:
    corners = [
        (width / 2 - radius, height / 2 - radius, 0.0),
        (-width / 2 + radius, height / 2 - radius, 90.0),
        (-width / 2 + radius, -height / 2 + radius, 180.0),
        (width / 2 - radius, -height / 2 + radius, 270.0),
    ]
    points = []
    for cx, cy, start in corners:
        for k in range(segments + 1):
            a = math.radians(start + 90.0 * k / segments)
            points.append((cx + radius * math.cos(a), cy + radius * math.sin(a)))
    return np.array(points)


def _regular_polygon(circumradius: float, sides: int) -> NDArray:
    angles = np.arange(sides) * 2.0 * math.pi / sides
    return np.stack([circumradius * np.cos(angles), circumradius * np.sin(angles)], axis=-1)


WORKPIECE_SHAPES: dict[str, WorkpieceShape] = {
    shape.name: shape
    for shape in (
        WorkpieceShape.from_outline(
            "rect-120x80",
            [(-60, -40), (60, -40), (60, 40), (-60, 40)],
            180.0,
            "rectangular plate 120 × 80 mm",
        ),
        WorkpieceShape.from_outline(
            "square-60",
            [(-30, -30), (30, -30), (30, 30), (-30, 30)],
            90.0,
            "square plate 60 × 60 mm",
        ),
        WorkpieceShape.from_outline(
            "l-bracket",
            [(0, 0), (100, 0), (100, 30), (30, 30), (30, 70), (0, 70)],
            360.0,
            "L bracket, legs 100 and 70 mm, 30 mm wide",
        ),
        WorkpieceShape.from_outline(
            "hexagon", _regular_polygon(45.0, 6), 60.0, "hexagonal plate, 90 mm across corners"
        ),
        WorkpieceShape.from_outline(
            "disc-70",
            _regular_polygon(35.0, 180),
            0.0,
            "round plate Ø70 mm (180-gon, within 0.005 mm of a circle)",
        ),
        WorkpieceShape.from_outline(
            "rounded-rect-100x60",
            _rounded_rect(100.0, 60.0, 12.0),
            180.0,
            "plate 100 × 60 mm with 12 mm corner radii",
        ),
    )
}

# Bead-blasted aluminium: bright against the dark table, a little darker than marker paper.
WORKPIECE_BGR = (190.0, 193.0, 196.0)


@dataclass(frozen=True)
class Workpiece:
    """A flat part lying on the table (thickness ignored: its outline is on z = 0).

    The pose puts the shape's area centroid at (x_mm, y_mm) and turns it by `rotation_deg`
    counter-clockwise seen from above (from robot +x towards +y).
    """

    shape: WorkpieceShape
    x_mm: float
    y_mm: float
    rotation_deg: float = 0.0
    colour_bgr: tuple[float, float, float] = WORKPIECE_BGR

    @classmethod
    def named(
        cls, shape: str | WorkpieceShape, x_mm: float, y_mm: float, rotation_deg: float = 0.0
    ) -> Workpiece:
        """A workpiece of a library shape (see WORKPIECE_SHAPES) at a pose on the table."""
        if isinstance(shape, str):
            try:
                shape = WORKPIECE_SHAPES[shape]
            except KeyError:
                known = ", ".join(sorted(WORKPIECE_SHAPES))
                raise ValueError(f"no workpiece shape {shape!r}; known shapes: {known}") from None
        return cls(shape, float(x_mm), float(y_mm), float(rotation_deg))

    @property
    def name(self) -> str:
        return self.shape.name

    def outline_table_mm(self) -> NDArray[np.float64]:
        """The outline's vertices on the table (N×2, robot frame mm)."""
        a = math.radians(self.rotation_deg)
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        return np.asarray(self.shape.outline_mm) @ rot.T + (self.x_mm, self.y_mm)

    def centroid_table_mm(self) -> NDArray[np.float64]:
        """Area centroid of the outline on the table (equals (x_mm, y_mm) by construction)."""
        return polygon_area_centroid(self.outline_table_mm())[1]
