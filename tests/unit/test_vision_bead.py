"""The bead finder on frames the simulated camera renders: clean beads pass on several parts
and poses, each defect is found with its reason, the annotated image is drawn.

The bead is laid by `bead_offline.lay_bead` (the records a run leaves: the robot's timed path,
the glue's history) and rendered through the camera model with its noise and light; the
inspection sees only the undistorted frame, the plan and the calibration fitted on the
markers as the cell's would be.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

from server.drivers.sim.bead_offline import Defects, lay_bead
from server.drivers.sim.camera_degradations import Degradations
from server.drivers.sim.camera_model import DEFAULT_CAMERA_MODEL, shifted_camera
from server.drivers.sim.camera_scene import Scene, render_table
from server.settings.model import Settings
from server.vision.bead import (
    BeadSegment,
    BeadTolerances,
    annotate_bead,
    expected_bead_width_mm,
    inspect_bead,
)
from server.vision.homography import PlaneCalibration, fit_plane_calibration
from server.vision.intrinsics import Intrinsics, Undistorter
from server.vision.paths import SprayPattern, spray_polylines

MODEL = DEFAULT_CAMERA_MODEL
SPEED, FLOW = 100.0, 30.0
TOLERANCES = BeadTolerances.from_settings(Settings())
CLEAN = Defects()
PATTERN = SprayPattern(outline_offset_mm=-6.0, fill="raster", fill_spacing_mm=20.0)


@functools.cache
def undistorter() -> Undistorter:
    return Undistorter(Intrinsics(MODEL.camera_matrix, np.array(MODEL.dist), MODEL.size))


@functools.cache
def calibration() -> PlaneCalibration:
    """The table's calibration from where the markers appear in the undistorted frame."""
    markers = Scene().marker_positions_mm
    centres = undistorter().points(MODEL.table_to_pixel(np.asarray(markers)))
    return fit_plane_calibration(dict(enumerate(centres)), dict(enumerate(markers)))


def inspect(
    placement: tuple[str, float, float, float],
    defects: Defects = CLEAN,
    *,
    degradations: Degradations | None = None,
    knocked_mm: float = 0.0,
):
    scene = Scene(degradations=degradations)
    part = scene.place_workpiece(*placement)
    lines = spray_polylines(part.outline_table_mm(), PATTERN)
    scene.bead = lay_bead(lines, SPEED, FLOW, defects)
    if defects.shift is not None:
        scene.shift_workpieces(defects.shift[0], defects.shift[1])
    model = shifted_camera(MODEL, knocked_mm, 0.0) if knocked_mm else MODEL
    frame = undistorter()(render_table(scene, model, np.random.default_rng(7)))
    width = expected_bead_width_mm(FLOW, SPEED)
    segments = [BeadSegment(i + 1, part.name, line, width) for i, line in enumerate(lines)]
    return frame, segments, inspect_bead(frame, segments, calibration(), TOLERANCES)


CLEAN_PARTS = [
    ("rect-120x80", 330.0, 60.0, 5.0),
    ("hexagon", 300.0, -130.0, 17.0),
    ("rounded-rect-100x60", 520.0, -140.0, -35.0),
    ("l-bracket", 520.0, 110.0, 120.0),
]


def test_the_width_follows_flow_over_speed() -> None:
    assert expected_bead_width_mm(30.0, 100.0) == pytest.approx(3.57, abs=0.01)
    # the cross-section is the volume per mm: twice the flow or half the speed, √2 the width
    assert expected_bead_width_mm(60.0, 100.0) == pytest.approx(3.57 * 2**0.5, abs=0.01)
    assert expected_bead_width_mm(30.0, 50.0) == expected_bead_width_mm(60.0, 100.0)
    assert expected_bead_width_mm(0.0, 100.0) == 0.0
    with pytest.raises(ValueError, match="speed"):
        expected_bead_width_mm(30.0, 0.0)


@pytest.mark.parametrize("placement", CLEAN_PARTS, ids=[p[0] for p in CLEAN_PARTS])
def test_a_clean_bead_passes_and_is_measured(placement) -> None:
    _, segments, findings = inspect(placement)
    assert [f.index for f in findings] == [s.index for s in segments]
    for finding in findings:
        assert finding.problems == [], finding.problems
        assert finding.width_mean_mm == pytest.approx(expected_bead_width_mm(FLOW, SPEED), rel=0.1)
        assert finding.offset_mean_mm is not None and finding.offset_mean_mm < 0.3
        assert finding.longest_gap_mm <= TOLERANCES.max_gap_mm


def test_a_clean_bead_passes_on_a_camera_with_every_degradation() -> None:
    _, _, findings = inspect(CLEAN_PARTS[0], degradations=Degradations.realistic())
    assert [p for f in findings for p in f.problems] == []


def problems(findings) -> list[str]:
    return [p for f in findings for p in f.problems]


def test_a_clogged_nozzle_is_a_narrow_bead() -> None:
    _, _, findings = inspect(CLEAN_PARTS[0], Defects(clog_fraction=0.35))
    found = problems(findings)
    assert found and all("wide" in p and "blockage" in p for p in found), found
    assert all(f.width_mean_mm < 0.7 * expected_bead_width_mm(FLOW, SPEED) for f in findings)


def test_a_nozzle_clogging_half_way_is_found_on_the_stretch_it_thinned() -> None:
    _, _, findings = inspect(CLEAN_PARTS[0], Defects(clog_fraction=0.3, clog_from_s=2.0))
    assert any("wide over" in p or "wide on average" in p for p in problems(findings))


def test_a_late_valve_leaves_a_gap_at_each_segment_start() -> None:
    _, _, findings = inspect(CLEAN_PARTS[0], Defects(valve_delay_s=0.1))
    first = findings[0]
    assert first.gaps_mm and first.gaps_mm[0][0] < 3.0 and first.longest_gap_mm > 6.0
    assert "segment 1: a gap of" in first.problems[0] and "(at most 3.0 mm)" in first.problems[0]


def test_a_valve_closed_over_a_stretch_is_a_gap_where_it_was() -> None:
    _, _, findings = inspect(CLEAN_PARTS[0], Defects(gap=(0, 80.0, 12.0)))
    gap = max(findings[0].gaps_mm, key=lambda g: g[1] - g[0])
    assert gap[0] == pytest.approx(80.0, abs=2.0) and gap[1] - gap[0] == pytest.approx(12, abs=3)
    assert [f.index for f in findings if f.problems] == [1]


def test_a_part_shifted_while_spraying_carries_its_bead_off_the_path() -> None:
    _, _, findings = inspect(CLEAN_PARTS[0], Defects(shift=(3.0, -2.0, 0.5)))
    offsets = [p for p in problems(findings) if "off its planned path" in p]
    assert offsets and "part did not move" in offsets[0]


def test_a_knocked_camera_shows_the_bead_off_its_path() -> None:
    _, _, findings = inspect(CLEAN_PARTS[0], knocked_mm=2.0)
    # the outline runs both ways, so a knock along x shows across its legs along y
    assert findings[0].offset_max_mm is not None and findings[0].offset_max_mm > 1.5
    assert any("calibration" in p for p in findings[0].problems)


def test_no_bead_at_all_is_said_so() -> None:
    scene = Scene()
    part = scene.place_workpiece(*CLEAN_PARTS[0])
    frame = undistorter()(render_table(scene, MODEL, np.random.default_rng(1)))
    lines = spray_polylines(part.outline_table_mm(), PATTERN)
    segments = [BeadSegment(i + 1, part.name, line, 3.6) for i, line in enumerate(lines)]
    findings = inspect_bead(frame, segments, calibration(), TOLERANCES)
    assert all(f.problems and "no bead found" in f.problems[0] for f in findings)
    assert findings[0].as_dict()["width_mean_mm"] is None


def test_the_annotated_image_marks_the_findings() -> None:
    frame, segments, findings = inspect(CLEAN_PARTS[0], Defects(gap=(0, 80.0, 12.0)))
    annotated = annotate_bead(frame, segments, findings, calibration())
    assert annotated.shape == frame.shape and annotated.dtype == np.uint8
    changed = np.any(annotated != frame, axis=2)
    assert changed.sum() > 1000  # plan, bead, gap and verdict drawn
    red = (annotated[..., 2] > 200) & (annotated[..., 1] < 80) & (annotated[..., 0] < 80)
    assert red.sum() > 100  # the gap (and the verdict) in red
    record = findings[0].as_dict()
    assert set(record) == {
        "index", "workpiece_id", "length_mm", "width_mean_mm", "width_min_mm", "width_max_mm",
        "gaps_mm", "longest_gap_mm", "offset_mean_mm", "offset_max_mm", "problems",
    }  # fmt: skip


def _stamp(annotated: np.ndarray) -> tuple[int, int]:
    """Green and red pixels of the verdict's stamp (the top-left corner where it is drawn)."""
    corner = annotated[15:60, 15:330].astype(int)
    blue, green, red = corner[..., 0], corner[..., 1], corner[..., 2]
    greens = int(((green > 150) & (red < 120) & (blue < 120)).sum())
    reds = int(((red > 180) & (green < 100) & (blue < 100)).sum())
    return greens, reds


def test_the_stamp_follows_the_parts_verdict_not_the_bead_alone() -> None:
    """A clean bead on a part judged defective on its glue volume is stamped DEFECTIVE,
    in red: the stamp says the part's verdict, which weighs more than the bead."""
    frame, segments, findings = inspect(CLEAN_PARTS[0])
    assert not [p for f in findings for p in f.problems]
    volume = "glue dispensed 2.588 ml, 144 % of the 1.797 ml the path needs"
    judged = annotate_bead(frame, segments, findings, calibration(), reasons=[volume])
    greens, reds = _stamp(judged)
    assert reds > 200 and greens < 20, (greens, reds)
    good = annotate_bead(frame, segments, findings, calibration(), reasons=[])
    greens, reds = _stamp(good)
    assert greens > 200 and reds < 20, (greens, reds)
