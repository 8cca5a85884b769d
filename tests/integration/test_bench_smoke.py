"""The WebSocket fan-out and REST throughput benchmarks run end to end.

Tiny counts, real servers in their own processes, real sockets: this keeps
the benchmarks working as the server changes, and checks that what they
report is coherent (every client got every transition, no request failed,
percentiles in order). No timing is asserted: that is what the benchmarks
report, not what a test can promise. Results go to tmp_path, never over the
published figures in bench/results.
"""

from __future__ import annotations

import gc
import json
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from bench import (
    bead_inspection,
    cycle_time,
    device_feed,
    engine_throughput,
    estop_doors,
    estop_latency,
    estop_under_attack,
    memory,
    pause_latency,
    planning,
    plant_latency,
    recording_cost,
    reset_probe,
    rest_throughput,
    scaling,
    self_watch,
    startup,
    vision,
    vision_accuracy,
    ws_fanout,
)
from bench.report import RESULTS_ENV, emit

LATENCY_KEYS = {"p50_ms", "p99_ms", "max_ms", "n"}


@pytest.fixture(autouse=True)
def results_in_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv(RESULTS_ENV, str(tmp_path))
    return tmp_path


@pytest.fixture(autouse=True)
def leaves_no_temporary_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """A benchmark removes what it made: the e-stop run left 50 MB per run behind.

    multiprocessing's own directory (pymp-*) lives as long as the process that
    made it, so it is not counted.
    """
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    monkeypatch.setenv("TMPDIR", str(scratch))
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    yield
    left = sorted(p.name for p in scratch.iterdir() if not p.name.startswith("pymp-"))
    assert not left, f"the benchmark left {left} in the temporary directory"


@pytest.fixture(autouse=True)
def restore_garbage_collection() -> Iterator[None]:
    """Benchmarks that host the server tune the collector as `python -m server` does."""
    thresholds = gc.get_threshold()
    yield
    gc.unfreeze()
    gc.set_threshold(*thresholds)


def assert_ordered_latencies(row: dict[str, Any]) -> None:
    assert row.keys() >= LATENCY_KEYS
    assert row["n"] > 0
    assert 0 < row["p50_ms"] <= row["p99_ms"] <= row["max_ms"]


def written_rows(directory: Path, name: str) -> list[dict[str, Any]]:
    return json.loads((directory / f"{name}.json").read_text(encoding="utf-8"))["rows"]


def test_emit_writes_to_the_given_directory(tmp_path: Path) -> None:
    target = tmp_path / "elsewhere"
    path = emit("probe", [{"measure": "x", "n": 1}], results_dir=target)
    assert path == target / "probe.json"
    assert written_rows(target, "probe") == [{"measure": "x", "n": 1}]


def test_ws_fanout_every_client_gets_every_transition(results_in_tmp: Path) -> None:
    transitions = 6
    rows = ws_fanout.main(["--clients", "2,5", "--transitions", str(transitions)])
    assert [row["clients"] for row in rows] == [2, 5]
    for row in rows:
        assert_ordered_latencies(row)
        assert row["transitions"] == transitions
        assert row["n"] == row["clients"] * transitions
        assert row["everyone_p99_ms"] <= row["max_ms"]
        assert (row["complete"], row["dropped_told"], row["missing"]) == (row["clients"], 0, 0)
        assert row["server_cpu_s"] > 0
    assert written_rows(results_in_tmp, "ws_fanout") == rows


def test_rest_throughput_compares_state_with_a_bare_endpoint(results_in_tmp: Path) -> None:
    argv = ["--concurrency", "4", "--duration", "0.5", "--warmup", "0.2", "--profile", "always"]
    rows = rest_throughput.main([*argv, "--rounds", "3"])
    assert [row["target"] for row in rows] == ["cell GET /state", "bare FastAPI GET /state"]
    for row in rows:
        assert_ordered_latencies(row)
        assert row["errors"] == 0
        assert row["requests"] == row["n"]
        assert row["req_per_s"] > 0
    assert rows[0]["ratio_to_bare"] == pytest.approx(
        rows[0]["req_per_s"] / rows[1]["req_per_s"], rel=0.01
    )
    document = json.loads((results_in_tmp / "rest_throughput.json").read_text(encoding="utf-8"))
    assert document["rows"] == rows
    assert document["state_body_bytes"] == document["bare_body_bytes"] > 100
    rounds = document["rounds"]
    assert len(rounds) == 3 and all(row["rounds"] == 3 for row in rows)
    # each row is its target's median round
    assert rows[0]["req_per_s"] == sorted(r["cell_req_per_s"] for r in rounds)[1]
    assert rows[1]["req_per_s"] == sorted(r["bare_req_per_s"] for r in rounds)[1]
    # the CPU comparison: the bare server's CPU per request over the cell's, median round
    cpu_ratios = sorted(r["bare_cpu_us"] / r["cell_cpu_us"] for r in rounds)
    assert rows[0]["cpu_ratio_to_bare"] == pytest.approx(cpu_ratios[1], abs=0.001)
    profile = document["cell_profile"]
    assert profile["requests_profiled"] > 0
    assert "server/api/queries.py" in " ".join(profile["cell_code_cumulative_us_per_request"])


def test_engine_throughput_compares_with_both_libraries(results_in_tmp: Path) -> None:
    rows = engine_throughput.main(["--events", "800", "--profile"])
    by_what = {row["what"].split(" ")[0]: row for row in rows}
    assert by_what.keys() == {"engine", "transitions", "python-statemachine", "worker"}
    assert all(row["events"] == 800 and row["events_per_s"] > 0 for row in rows)
    profile = written_rows(results_in_tmp, "engine_throughput_worker_profile")
    assert {row["area"] for row in profile} >= {"asyncio loop, tasks, futures"}


def test_estop_latency_measures_every_condition(results_in_tmp: Path) -> None:
    rows = estop_latency.main(["--trials", "3", "--ws-clients", "5", "--queue-size", "50"])
    assert [row["condition"] for row in rows] == [
        condition.replace("1000", "5") for condition in estop_latency.CONDITIONS
    ]
    for row in rows:
        assert_ordered_latencies(row)
        assert row["n"] == 3
        # The answer comes after both devices had the stop (it waits for their replies).
        assert row["answer_p50_ms"] >= row["to_sockets_p50_ms"] > 0
        assert 0 <= row["line_busy_stops"] <= row["n"]


def test_estop_under_attack_measures_quiet_and_attacked_stops(results_in_tmp: Path) -> None:
    argv = ["--trials", "3", "--slow-clients", "20", "--slow-addresses", "2"]
    rows = estop_under_attack.main([*argv, "--flood-connections", "1", "--settle", "0.2"])
    assert [row["condition"] for row in rows] == [
        "quiet",
        "20 slow clients + bad-token flood (1 connections)",
    ]
    for row in rows:
        assert_ordered_latencies(row)
        assert row["n"] == 3 and row["not_202"] == 0
    document = json.loads((results_in_tmp / "estop_under_attack.json").read_text("utf-8"))
    attack = document["attack"]
    assert attack["slow_connections_made"] >= 20
    assert attack["flood_answers"]["401"] == 20 and attack["flood_answers"]["429"] > 0
    assert document["server_open_fds"]["attacked_max"] > 0


def test_estop_doors_measures_every_door_quiet_and_flooded(results_in_tmp: Path) -> None:
    floods = ["--mqtt-flood", "20", "--opcua-flood", "10", "--http-flood", "10"]
    rows = estop_doors.main(["--trials", "1", *floods])
    assert [(row["door"], row["condition"].split(" ")[0]) for row in rows] == [
        (door, condition)
        for door in ("http", "mqtt", "opcua")
        for condition in ("quiet", "flooded", "behind")
    ]
    for row in rows:
        assert row["n"] == 1 and row["p50_ms"] > 0
        # the frames leave the server before a device can note them: both parts are
        # real spans of the one stop, and together they are its time from the wire
        assert row["server_p50_ms"] > 0 and row["devices_p50_ms"] > 0
        parts = row["server_p50_ms"] + row["devices_p50_ms"]
        assert abs(parts - row["written_p50_ms"]) < 0.01
    assert (results_in_tmp / "estop_doors.json").is_file()


def test_reset_probe_measures_every_condition(results_in_tmp: Path) -> None:
    rows = reset_probe.main(["--trials", "2", "--slow-trials", "1"])
    assert [row["n"] for row in rows] == [2, 1, 1]
    for row in rows:
        assert_ordered_latencies(row)
    assert written_rows(results_in_tmp, "reset_probe") == rows


def test_plant_latency_sees_every_transition_on_mqtt_sparkplug_and_opcua(
    results_in_tmp: Path,
) -> None:
    """Two cycles of five cells (e-stop, reset, start, e-stop while spraying, reset):
    5 transitions × 3 MQTT cells × 2 cycles on the broker, 5 × 2 in cell-1's Sparkplug
    DDATA and 5 × 2 on cell-1's OPC UA subscription, each with the server's write time;
    cell-1's alarm events; then the
    same two cycles of cell-1 alone, each seen once on every interface; per condition,
    one device stop and one answer per cycle of each of the three cells compared
    (cell-1, plain and the control)."""
    rows = plant_latency.main(["--cycles", "2"])
    counts = [row["n"] for row in rows]
    # per phase: MQTT, Sparkplug, OPC UA data change, alarm events, CellState written
    assert counts[:3] == [30, 10, 10] and counts[5:8] == [10, 10, 10], counts
    assert counts[4] == counts[9] == 10, counts
    assert counts[10:] == [2] * 12, counts
    for alarm in (rows[3], rows[8]):
        assert alarm["figure"].startswith("alarm") and alarm["n"] > 0, alarm
    for row in rows:
        assert_ordered_latencies(row)
    assert written_rows(results_in_tmp, "plant_latency") == rows


def test_pause_latency_reports_each_measure(results_in_tmp: Path) -> None:
    rows = pause_latency.main(["--trials", "3"])
    assert [row["measure"] for row in rows] == ["total", "valve_closed", "robot_still", "answered"]
    for row in rows:
        assert row["n"] == 3 and row["p50_ms"] <= row["p99_ms"] <= row["max_ms"]
    assert rows[0]["p50_ms"] > 0


def test_self_watch_times_each_step(results_in_tmp: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # A limit the process is over: the looks raise the memory warning, as they do in a
    # test process holding many cells, and the bench's quiet sink takes it.
    tiny = self_watch.WatchSettings(memory_limit="1MB")
    monkeypatch.setattr(self_watch, "WatchSettings", lambda: tiny)
    rows = self_watch.main(["--looks", "5", "--parts", "20"])
    assert [row["n"] for row in rows] == [5, 5, 20, 1]
    for row in rows:
        assert 0 <= row["p50_ms"] <= row["p99_ms"] <= row["max_ms"]


def test_memory_and_scaling_report_every_point(results_in_tmp: Path) -> None:
    memory_rows = memory.main(["--events", "400", "--operations", "20"])
    assert memory_rows[0]["growth_mb"] == 0
    assert all(row["rss_mb"] > 0 for row in memory_rows)
    sweeps = scaling.main(
        [
            "--depths", "0,20",
            "--depth-repeats", "3",
            "--clients", "2",
            "--journal-sizes", "0,500",
            "--requests", "5",
            "--transitions", "3",
        ]
    )  # fmt: skip
    assert [row["queue_depth"] for row in sweeps["queue_depth"]] == [0, 20]
    for row in sweeps["queue_depth"]:
        assert row["repeats"] == 3
        assert row["estop_decided_p50_ms"] <= row["estop_decided_p99_ms"]
        assert row["estop_decided_p99_ms"] <= row["estop_decided_max_ms"]
    assert [row["journal_events"] for row in sweeps["journal_size"]] == [0, 500]
    assert sweeps["ws_clients"][0]["ws_clients"] == 2
    assert (results_in_tmp / "scaling.png").stat().st_size > 10_000


def test_device_feed_reports_ages_and_the_silence_detection(results_in_tmp: Path) -> None:
    rows = device_feed.main(["--runs", "1", "--silences", "2"])
    assert [row["measure"].split(":")[0] for row in rows[:3]] == ["device message"] * 3
    for row in rows:
        assert 0 <= row["p50_ms"] <= row["p99_ms"] <= row["max_ms"]  # a fresh pose is 0 ms old
    assert "VALVE_UNCONFIRMED" in rows[3]["measure"] and rows[3]["n"] == 2
    assert written_rows(results_in_tmp, "device_feed") == rows


def test_planning_measures_the_library_while_plans_are_cancelled(results_in_tmp: Path) -> None:
    rows = planning.main(["--repeats", "1", "--cycles", "2", "--idle", "0.3"])
    assert [row["condition"].split(" ")[0] for row in rows] == [
        "idle",
        "control:",
        "worst",
        "issue's",
    ]
    for row in rows:
        assert_ordered_latencies(row)
        assert row["server_rss_mb"] > 0
    for row in rows[1:]:
        assert row["cycles"] == 2
        assert 0 < row["cancel_to_idle_p50_ms"] <= row["cancel_to_idle_max_ms"]
    document = json.loads((results_in_tmp / "planning.json").read_text(encoding="utf-8"))
    assert document["rows"] == rows
    worst = document["worst_allowed_part"]
    assert worst["points"] <= 500 and worst["fill_lines"] <= 1000
    assert 1500 < worst["fill_strokes"] <= 2000  # at the limit: the finest spacing accepted
    assert 0 < worst["plan_s_median"] <= worst["plan_s_max"]


def test_vision_detection_runs_every_path_on_small_and_large_markers() -> None:
    for marker_px in (45, 150):
        rows = vision.detection_rows(2, marker_px)
        assert [row["measure"].split(":")[0] for row in rows] == [f"ArUco {marker_px} px"] * 4
        for row in rows:
            assert_ordered_latencies(row)
            assert row["markers_found_min"] == 9
        for row in rows[1:]:
            assert row["max_centre_error_vs_truth_px"] < 1.0  # the right marker, not a look-alike


def test_vision_accuracy_reports_calibration_and_matching(results_in_tmp: Path) -> None:
    rows = vision_accuracy.main(["--seeds", "1", "--only", "clean", "--only", "all together"])
    assert [row["condition"] for row in rows] == ["clean", "all together"]
    for row in rows:
        assert 0 < row["calibration_field_mean_mm"] <= row["calibration_field_max_mm"]
        assert 0 < row["match_outline_mean_mm"] <= row["match_outline_max_mm"]
    assert written_rows(results_in_tmp, "vision_accuracy") == rows


def test_cycle_time_compares_runs_with_and_without_inspection(results_in_tmp: Path) -> None:
    rows = cycle_time.main(["--runs", "1", "--block", "1"])
    assert [row["measure"] for row in rows[:5]] == [
        "cycle, neither",
        "cycle, retract",
        "cycle, inspection",
        "cycle, both",
        "inspection itself",
    ]
    for row in rows:
        assert_ordered_latencies(row)
    assert [row["n"] for row in rows[:5]] == [1, 1, 1, 1, 2]
    steps = {row["measure"] for row in rows[5:]}
    for step in ("frame: whole capture", "analysis", "inspection: after clearance"):
        assert f"step (inspection): {step}" in steps
        assert f"step (both): {step}" in steps
    for step in ("retract: to clearance", "retract: after clearance"):
        assert f"step (both): {step}" in steps
    assert written_rows(results_in_tmp, "cycle_time") == rows


def test_recording_cost_compares_journal_bytes_with_the_recorder_on_and_off(
    results_in_tmp: Path,
) -> None:
    rows = recording_cost.main(["--runs", "1"])
    on, off, samples, _ = rows
    assert on["median"] > off["median"] > 0  # the samples cost bytes; a run costs some anyway
    assert samples["median"] > 0
    assert written_rows(results_in_tmp, "recording_cost") == rows


def test_bead_inspection_reports_rates_and_times(results_in_tmp: Path) -> None:
    rows = bead_inspection.main(["--parts", "4", "--seed", "3"])
    kinds = [row["defect"] for row in rows]
    assert kinds == [*bead_inspection.KINDS, "all"]
    summary = rows[-1]
    assert summary["parts"] == 4 == sum(row["parts"] for row in rows[:-1])
    assert 0 < summary["inspection_p50_ms"] <= summary["inspection_p95_ms"]
    assert 0 <= summary["false_alarm_rate_percent"] <= 100
    assert written_rows(results_in_tmp, "bead_inspection") == rows


def test_cell_memory_lists_every_process_of_both_layouts_and_soaks(results_in_tmp: Path) -> None:
    soak = ["--soak-minutes", "0.02", "--every-minutes", "0.001"]
    rows = memory.main(["--cell", "--runs", "1", "--layouts", "sim,devices", *soak])
    for layout in ("sim", "devices"):
        mine = [row for row in rows if row["layout"] == layout]
        totals = [row["point"] for row in mine if row["process"] == "cell total"]
        assert totals[:2] == ["started", "after 1 run"]
        assert len(totals) > 2 and all(point.startswith("soak ") for point in totals[2:])
        assert {"server", "image process", "cell total"} <= {row["process"] for row in mine}
        for row in mine:
            assert 0 < row["unique_mb"] <= row["pss_mb"] <= row["rss_mb"]
    apart = {row["process"] for row in rows if row["layout"] == "devices"}
    simulators = ("robot simulator", "glue simulator", "camera stream")
    assert {f"{name} (not counted)" for name in simulators} <= apart
    saved = json.loads((results_in_tmp / "memory_cell.json").read_text())
    assert set(saved["unique_total_mb"]) == {"sim", "devices"}


def test_startup_reads_every_phase_of_each_start(results_in_tmp: Path) -> None:
    rows = startup.main(["--rows", "300", "--starts", "2"])
    phases = {row["phase"]: row for row in rows}
    assert set(phases) == {
        "main", "app built", "journal check", "robot", "glue", "camera", "port open", "idle"
    }  # fmt: skip
    for row in rows:
        assert row["n"] == 2 and 0 <= row["min_s"] <= row["median_s"] <= row["max_s"]
    assert phases["main"]["median_s"] < phases["idle"]["median_s"]
    saved = json.loads((results_in_tmp / "startup.json").read_text())
    assert saved["rows"] == 300 and len(saved["starts"]) == 2
