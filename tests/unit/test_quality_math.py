"""The quality maths on hand-written samples: precision, dispensing, segments, CSV columns."""

from __future__ import annotations

import json

import numpy as np
import pytest

from server.drivers.base import Pose
from server.quality.csv_columns import INSPECTION_COLUMNS, inspection_values
from server.quality.dispensing import OPENING_TRANSIENT_S, dispensing_consistency
from server.quality.model import FlowSample, PlannedSegment, PoseSample, SprayWindow, spray_segments
from server.quality.precision import distance_to_polyline, trajectory_precision


def _segment(index: int = 1, speed: float = 100.0, flow: float = 30.0) -> PlannedSegment:
    return PlannedSegment(
        index, "p", np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 50.0]]), speed, flow
    )


def test_distance_is_to_the_line_not_to_its_vertices() -> None:
    line = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 50.0]])
    d = distance_to_polyline(np.array([[50.0, 2.0], [103.0, 25.0], [-4.0, 3.0]]), line)
    assert d == pytest.approx([2.0, 3.0, 5.0])


def test_precision_per_segment_and_run_wide() -> None:
    samples = [
        PoseSample(0, 10.0, 1.0, 1),
        PoseSample(0, 20.0, -3.0, 1),
        PoseSample(0, 100.0, 10, 2),
    ]
    result = trajectory_precision(samples, [_segment(1), _segment(2), _segment(3)])
    first, second, third = result["segments"]
    assert (first["mean_mm"], first["max_mm"], first["samples"]) == (2.0, 3.0, 2)
    assert second["max_mm"] == 0.0
    assert third == {"index": 3, "samples": 0, "mean_mm": None, "max_mm": None}
    assert result["max_mm"] == 3.0 and result["mean_mm"] == pytest.approx(4 / 3, abs=1e-3)
    assert result["p95_mm"] == pytest.approx(np.percentile([1.0, 3.0, 0.0], 95), abs=1e-3)


def test_dispensing_cv_time_out_of_tolerance_and_glue() -> None:
    segment = _segment()  # 150 mm at 100 mm/s, 30 ml/min: 1.5 s, 0.75 ml
    window = SprayWindow(1, 10.0, 11.5)
    readings = [10.0 + 0.1 * i for i in range(15)]
    flows = [FlowSample(t, 30.0 if t < 11.0 else 15.0, 30.0, True) for t in readings]
    flows.append(FlowSample(12.0, 0.0, 30.0, False))  # after the close: not counted
    result = dispensing_consistency(flows, [window], [segment], 10.0)
    assert result["expected_ml"] == pytest.approx(0.75)
    # 1.0 s at 30 ml/min, then 0.5 s at 15: 0.5 + 0.125 ml.
    assert result["glue_ml"] == pytest.approx(0.625, abs=1e-3)
    assert result["out_of_tolerance_s"] == pytest.approx(0.5, abs=1e-6)
    judged = [f.flow_ml_min for f in flows if f.valve_open and f.at - 10.0 >= OPENING_TRANSIENT_S]
    expected_cv = np.std(judged, ddof=1) / np.mean(judged) * 100
    assert result["cv_percent"] == pytest.approx(expected_cv, abs=1e-3)
    assert result["glue_ratio_percent"] == pytest.approx(83.33, abs=0.01)
    assert result["glue_from"] == "flow readings"  # these readings carry no count


def test_the_glue_is_the_totaliser_s_count_however_sparse_the_readings() -> None:
    # Two windows; the readings in them are few and late (a busy machine), their flows
    # say nothing of what happened between them: the count before the first open and
    # after the last close, both read with the valve closed, is the glue.
    windows = [SprayWindow(1, 10.0, 11.0), SprayWindow(2, 11.2, 12.5)]
    flows = [
        FlowSample(9.5, 0.0, 30.0, False, 100.0),
        FlowSample(9.9, 0.0, 30.0, False, 100.0),
        FlowSample(10.9, 90.0, 30.0, True, 100.4),  # held to the close: 1.5 ml by the flows
        FlowSample(12.3, 30.0, 30.0, True, 101.1),
        FlowSample(12.45, 0.0, 30.0, False, 101.1),  # closed, but before the last close
        FlowSample(12.7, 0.0, 30.0, False, 101.2),
        FlowSample(13.0, 0.0, 30.0, False, 101.2),
    ]
    result = dispensing_consistency(flows, windows, [_segment()], 10.0)
    assert result["glue_ml"] == pytest.approx(1.2)
    assert result["glue_from"] == "totaliser"
    assert result["glue_ratio_percent"] == pytest.approx(160.0)


def test_without_a_count_after_the_close_the_flows_are_summed() -> None:
    window = SprayWindow(1, 10.0, 11.0)
    flows = [
        FlowSample(9.9, 0.0, 30.0, False, 100.0),
        FlowSample(10.5, 60.0, 30.0, True, 100.5),  # the monitor's next poll was lost
    ]
    result = dispensing_consistency(flows, [window], [_segment()], 10.0)
    assert result["glue_from"] == "flow readings"
    assert result["glue_ml"] == pytest.approx(1.0)  # 60 ml/min held over the whole second


def test_no_window_no_glue_figures() -> None:
    result = dispensing_consistency([], [], [_segment()], 10.0)
    assert result["glue_ml"] is None and result["cv_percent"] is None


def test_spray_segments_follow_consecutive_spray_waypoints() -> None:
    class W:
        def __init__(self, x: float, spray: bool) -> None:
            self.pose, self.spray, self.speed = Pose(x, 0.0, 0.0), spray, 50.0
            self.workpiece, self.flow_rate_ml_min = "p", 20.0

    path = [
        W(0, False),
        W(0, False),
        W(10, True),
        W(20, True),
        W(20, False),
        W(50, False),
        W(60, True),
    ]
    segments, owner = spray_segments(path)
    assert [s.index for s in segments] == [1, 2]
    assert segments[0].path_mm[:, 0].tolist() == [0, 10, 20]
    assert owner == {2: 1, 3: 1, 6: 2}
    assert segments[0].expected_ml == pytest.approx(20 / 60 * 20 / 50)


def test_csv_columns_from_the_result() -> None:
    summary = {"verdict": "defective", "reasons": ["a", "b"], "glue_ml": 1.5}
    values = inspection_values("trajectory", "completed", None, json.dumps({"inspection": summary}))
    row = dict(zip(INSPECTION_COLUMNS, values, strict=True))
    assert (row["verdict"], row["reasons"], row["inspected"], row["glue_ml"]) == (
        "defective",
        "a | b",
        "yes",
        1.5,
    )
    assert inspection_values("calibrate_robot", "completed", None, None) == [""] * len(
        INSPECTION_COLUMNS
    )


def test_csv_columns_of_a_stopped_run_say_defective_not_inspected() -> None:
    values = inspection_values("trajectory", "failed", "EMERGENCY_STOP", None)
    row = dict(zip(INSPECTION_COLUMNS, values, strict=True))
    assert (row["verdict"], row["inspected"], row["glue_ml"]) == ("defective", "no", "")
    assert row["reasons"] == "run stopped: emergency stop (STOP)"
