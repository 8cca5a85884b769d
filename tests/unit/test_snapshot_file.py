"""The state snapshot file is written after a change has settled, and at stop at once."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from server.core import snapshot as snapshot_module
from server.core.snapshot import SnapshotFile


def test_a_change_is_written_once_it_settled_not_beside_its_journal_commit(
    tmp_path: Path,
) -> None:
    snapshot = SnapshotFile(tmp_path / "state.json", interval=3600, settle=3600)
    snapshot.start()
    snapshot.save({"state": "ERROR"})
    time.sleep(0.2)  # written at once before: long done by now
    assert not snapshot.path.exists()
    snapshot.stop()  # the last write is not held back
    assert json.loads(snapshot.path.read_text())["state"] == "ERROR"


def test_changes_while_settling_are_written_once_as_the_latest(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    written: list[str] = []
    monkeypatch.setattr(
        snapshot_module, "write_json_atomic", lambda _p, d: written.append(d["state"])
    )
    snapshot = SnapshotFile(tmp_path / "state.json", interval=3600, settle=3600)
    snapshot.start()
    for state in ("EXECUTING_TRAJECTORY", "ERROR", "IDLE"):
        snapshot.save({"state": state})
    time.sleep(0.2)
    snapshot.stop()
    assert written == ["IDLE"]
