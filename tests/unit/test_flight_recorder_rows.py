"""The flight recorder's rows and batches, from `device` messages, without a feed or a disk."""

from __future__ import annotations

from typing import Any

import pytest

from server.settings.recording import RecordingSettings
from server.storage.journal.records import Record
from server.views.recording import FlightRecorder, sample_row


def message(x: float | None, robot_age_ms: float | None, valve: bool = False) -> dict[str, Any]:
    return {
        "glue": {"valve_open": valve, "flow_ml_min": 12.5, "pressure_psi": 40.0, "age_ms": 20.0},
        "robot": {
            "position": None if x is None else [x, 0.0, 50.0, 0.0, 180.0, 0.0],
            "age_ms": robot_age_ms,
        },
    }


def test_a_row_carries_when_each_device_reported_and_the_speed_between_poses() -> None:
    first, pose = sample_row(message(100.0, 0.0), 1000.0, "r1", None)
    assert first["speed_mm_s"] is None  # no earlier pose: no speed
    assert first["glue_at"] == pytest.approx(999.98)
    second, _ = sample_row(message(110.0, 50.0, valve=True), 1000.15, "r1", pose)
    assert second["pose_at"] == pytest.approx(1000.1)
    assert second["speed_mm_s"] == pytest.approx(100.0)  # 10 mm in 0.1 s
    assert second["valve_open"] is True and second["run_id"] == "r1"


def test_no_pose_read_yet_is_a_row_without_pose() -> None:
    row, pose = sample_row(message(None, None), 5.0, "r1", None)
    assert pose is None and row["x_mm"] is None and row["pose_at"] is None


class Journal:
    def __init__(self) -> None:
        self.appends: list[tuple[list[Record], bool]] = []

    def append(self, rows: list[Record], *, durable: bool = True) -> None:
        self.appends.append((rows, durable))


class Runs:
    def __init__(self) -> None:
        self.run: dict[str, Any] | None = None

    def current_run(self) -> dict[str, Any] | None:
        return self.run


def recorder(**settings: Any) -> tuple[FlightRecorder, Journal, Runs]:
    journal, runs = Journal(), Runs()
    made = FlightRecorder(RecordingSettings(**settings), journal, runs)  # type: ignore[arg-type]
    return made, journal, runs


def test_samples_of_a_run_are_written_in_batches_never_durable_and_the_rest_at_its_end() -> None:
    made, journal, runs = recorder(run_recording_flush_s=1.0)
    made.sample(message(0.0, 0.0), 0.0)  # no run: nothing kept
    runs.run = {"run_id": "r1"}
    for k in range(15):
        made.sample(message(float(k), 0.0), 10.0 + k * 0.1)
    assert [len(rows) for rows, _ in journal.appends] == [11]  # 10.0 .. 11.0: one second
    assert all(durable is False for _, durable in journal.appends)
    made.run_ended("r1")
    assert [len(rows) for rows, _ in journal.appends] == [11, 4]
    runs.run = None
    made.sample(message(0.0, 0.0), 20.0)
    assert len(journal.appends) == 2


def test_a_new_run_starts_its_own_batch_and_its_own_speed() -> None:
    made, journal, runs = recorder()
    runs.run = {"run_id": "r1"}
    made.sample(message(0.0, 0.0), 1.0)
    runs.run = {"run_id": "r2"}
    made.sample(message(500.0, 0.0), 1.1)  # far away, but a new run: no speed from r1
    made.flush()
    first, second = (rows for rows, _ in journal.appends)
    assert first[0].params[1] == "r1" and second[0].params[1] == "r2"
    assert "speed_mm_s" in second[0].sql
    assert second[0].params[6] is None


def test_the_same_pose_report_twice_keeps_the_speed_last_measured() -> None:
    made, journal, runs = recorder()
    runs.run = {"run_id": "r1"}
    made.sample(message(0.0, 0.0), 1.0)
    made.sample(message(10.0, 0.0), 1.1)
    made.sample(message(10.0, 100.0), 1.2)  # the pose read at 1.1 again
    made.flush()
    speeds = [row.params[6] for row in journal.appends[0][0]]
    assert speeds[0] is None and speeds[1] == pytest.approx(100.0) == speeds[2]


def test_recording_off_keeps_nothing() -> None:
    made, journal, runs = recorder(run_recording=False)
    runs.run = {"run_id": "r1"}
    made.sample(message(0.0, 0.0), 1.0)
    made.run_ended("r1")
    made.flush()
    assert journal.appends == []
