"""How `gluectl line` reads the cells' MQTT topics (clients/line_model.py): pure folding."""

from __future__ import annotations

import json

import pytest

from clients.line_model import LineModel, split_topic
from clients.line_watch import Broker


def state(**extra: object) -> bytes:
    body = {"cell_id": "a", "state": "IDLE", "since": 5, "stop_reason": None, "run_id": None}
    return json.dumps(body | extra).encode()


def test_only_a_cells_four_topics_under_the_prefix_are_read() -> None:
    assert split_topic("glue", "glue/cell-1/kpis") == ("cell-1", "kpis")
    for topic in ("glue/cell-1/event", "plant/cell-1/state", "glue/cell-1/state/x", "glue//state"):
        assert split_topic("glue", topic) is None
    model = LineModel("glue")
    assert not model.apply("glue/a/event", b"{}")
    assert model.cells == {}


def test_status_state_stop_reason_and_oee() -> None:
    model = LineModel()
    model.apply("glue/a/status", json.dumps({"status": "online", "time": 5.0}).encode())
    model.apply("glue/a/state", state(state="ERROR", stop_reason={"code": "ESTOP", "message": "m"}))
    model.apply("glue/a/kpis", json.dumps({"oee": {"oee": 0.5}}).encode())
    (row,) = model.as_json()["cells"]
    assert row["online"] is True and row["state"] == "ERROR" and row["oee"] == 0.5
    assert row["stop_reason"] == {"code": "ESTOP", "message": "m"} and row["since"] == 5
    model.apply("glue/a/status", b"offline")
    assert model.cells["a"].online is False
    will = {"status": "offline", "time": None, "clean": False, "online_since": 5.0}
    model.apply("glue/a/status", b"online")  # a cell of an earlier release: the bare word
    assert model.cells["a"].online is True
    model.apply("glue/a/status", json.dumps(will).encode())
    assert model.cells["a"].online is False


def test_progress_is_shown_only_while_the_state_names_its_run() -> None:
    model = LineModel()
    model.apply("glue/a/state", state(state="EXECUTING_TRAJECTORY", run_id="r1"))
    model.apply("glue/a/progress", json.dumps({"run_id": "r1", "fraction": 0.3}).encode())
    assert model.cells["a"].shown_progress() == {"run_id": "r1", "fraction": 0.3}
    model.apply("glue/a/state", state(state="IDLE"))
    assert model.as_json()["cells"][0]["progress"] is None


def test_unreadable_payloads_change_nothing_and_rows_are_sorted() -> None:
    model = LineModel()
    assert not model.apply("glue/b/state", b"{not json")
    assert not model.apply("glue/b/kpis", b"[1]")
    model.apply("glue/b/status", b"online")
    model.apply("glue/a/status", b"garbled")
    assert [row.cell_id for row in model.rows()] == ["a", "b"]
    assert model.cells["a"].online is None


def test_broker_addresses() -> None:
    assert Broker.parse("mqtt://h:1884") == Broker("h", 1884)
    assert Broker.parse("mqtts://u:p@h") == Broker("h", 8883, True, "u", "p")
    for bad in ("http://h:1", "mqtt://", "mqtt://h:99999"):
        with pytest.raises(ValueError, match="not a broker address"):
            Broker.parse(bad)
