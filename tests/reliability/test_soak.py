"""The soak (tests/reliability/soak.py) in CI: a short run of the very code a long
soak runs, through its command line, plus proof that its journal and leak checks
can fail.

The long run itself (`python -m tests.reliability.soak --duration 30m`) is too
long for CI; this keeps its loop, its report and its verdict from rotting.
"""

from __future__ import annotations

import argparse
import json
import sqlite3
from pathlib import Path

import pytest

from server.storage.journal import Journal, records
from tests.reliability._journal_checks import (
    invalid_transitions,
    journaled_transitions,
    missing_events,
    operation_outcomes,
)
from tests.reliability.soak import find_leaks, main, parse_duration
from tests.reliability.soak_figures import FD_SLACK, Latencies, Sample

CI_DURATION = "20s"
CI_SEED = "20260517"


def test_a_short_soak_passes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status = main(["--duration", CI_DURATION, "--seed", CI_SEED, "--data", str(tmp_path)])
    out = capsys.readouterr().out
    report = json.loads(out.strip().splitlines()[-1])
    assert status == 0 and report["ok"], out
    assert report["cycles"] >= 4, out
    assert sum(report["faults_injected"].values()) >= 2, out
    assert report["operations_completed"] >= 1, out
    assert report["transitions_checked"] > 0 and report["events_acknowledged"] > 0, out
    assert report["resets_accepted"] >= 2, out  # every fault ended in a reset
    assert (tmp_path / "journal.db").is_file()
    # The crowd came: WebSocket clients churned and a burst of commands was answered.
    assert report["websocket"]["connections"] >= 1 and report["websocket"]["messages"] >= 1, out
    assert report["storm"]["bursts"] >= 1 and report["storm"]["commands"] >= 1, out
    # Sampled at both ends, at quiet moments, and judged.
    start, end = report["start"], report["end"]
    assert start is not None and start["at_s"] < end["at_s"], out
    assert end["websocket_clients"] == 0 and end["journal_mb"] > 0, out
    assert report["latency_end"]["GET /state"]["count"] >= 1, out
    assert report["leaks"] == [], out


def _sample(fds: int) -> Sample:
    return Sample(at_s=1.0, rss_mb=1.0, open_fds=fds, journal_mb=1.0, websocket_clients=0)


def test_the_leak_checks_find_a_leak() -> None:
    start = _sample(40)
    assert find_leaks(start, _sample(40 + FD_SLACK)) == []
    (grown,) = find_leaks(start, _sample(41 + FD_SLACK))
    assert "grew from 40 to" in grown
    stuck = Sample(at_s=2.0, rss_mb=1.0, open_fds=40, journal_mb=1.0, websocket_clients=3)
    assert find_leaks(start, stuck) == ["3 WebSocket clients still counted after all left"]
    assert find_leaks(None, stuck) == ["3 WebSocket clients still counted after all left"]


def test_latencies_are_kept_for_the_first_and_last_fifth_only() -> None:
    latencies = Latencies()
    latencies.add("GET /state", 5.0, 1.0)  # before the warm-up ended: not kept
    latencies.open_windows(warm_at=10.0, end_at=110.0)  # windows 10..30 and 90..
    for at in (10.0, 29.9, 30.0, 89.9, 90.0, 200.0):
        latencies.add("GET /state", at, at / 1000)
    start, end = latencies.figures(0)["GET /state"], latencies.figures(1)["GET /state"]
    assert (start.count, end.count) == (2, 2)
    assert start.p50_ms == 19.95 and end.p99_ms >= 190.0
    assert latencies.figures(0)["POST command"].count == 0


def _journal(path: Path) -> Path:
    """An empty journal with the server's own schema."""
    Journal(path).open()
    return path


def _transition(connection: sqlite3.Connection, old: str, event: str, new: str, eid: str) -> None:
    record = records.transition(
        {
            "timestamp": 1.0,
            "old_state": old,
            "new_state": new,
            "event": event,
            "event_id": eid,
            "time_in_old_state": 0.1,
        }
    )
    connection.execute(record.sql, record.params)


def test_the_journal_checks_find_what_is_wrong(tmp_path: Path) -> None:
    path = _journal(tmp_path / "journal.db")
    with sqlite3.connect(path) as connection:
        _transition(connection, "IDLE", "START_REQUESTED", "EXECUTING_TRAJECTORY", "a-1")
        _transition(connection, "EXECUTING_TRAJECTORY", "ERROR_OCCURRED", "ERROR", "a-2")
        _transition(connection, "ERROR", "START_REQUESTED", "EXECUTING_TRAJECTORY", "a-3")
        _transition(connection, "ERROR", "RESET_REQUESTED", "EXECUTING_TRAJECTORY", "a-4")
        for event_id in ("a-1", "a-2", "a-3"):
            record = records.event(event_id, 1.0, "START_REQUESTED", "api", {}, "accepted", "", "")
            connection.execute(record.sql, record.params)
        record = records.operation_started("a-1", "trajectory", 1.0, {})
        connection.execute(record.sql, record.params)
    connection.close()

    assert len(journaled_transitions(path)) == 4
    assert invalid_transitions(path) == [
        ("ERROR", "START_REQUESTED", "EXECUTING_TRAJECTORY"),
        ("ERROR", "RESET_REQUESTED", "EXECUTING_TRAJECTORY"),
    ]
    assert missing_events(path, {"a-1", "a-3", "a-4", "b-9"}) == {"a-4", "b-9"}
    assert missing_events(path, set()) == set()
    assert operation_outcomes(path) == {"running": 1}


def test_the_checks_refuse_a_missing_journal(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        invalid_transitions(tmp_path / "nowhere.db")
    assert not (tmp_path / "nowhere.db").exists()


@pytest.mark.parametrize(
    ("text", "seconds"),
    [("90s", 90), ("30m", 1800), ("2h", 7200), ("1h30m", 5400), ("45", 45), (" 1.5M ", 90)],
)
def test_durations(text: str, seconds: float) -> None:
    assert parse_duration(text) == seconds


@pytest.mark.parametrize("text", ["", "0", "0s", "m", "30x", "30m5", "-5s", "1h 30m"])
def test_bad_durations_are_refused(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError):
        parse_duration(text)
