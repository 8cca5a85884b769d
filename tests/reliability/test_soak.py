"""The soak (tests/reliability/soak.py) in CI: a short run of the very code a long
soak runs, through its command line, plus proof that its journal checks can fail.

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
from tests.reliability.soak import main, parse_duration

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
