"""The journal over HTTP: history, operations, errors, events, CSV, KPIs, metrics."""

from __future__ import annotations

import asyncio
import csv
import io
import sqlite3
import threading
from collections.abc import AsyncIterator
from typing import Any

import httpx
import pytest

from server.api import analytics
from server.bootstrap.cell import Cell
from server.cli.openapi import generate
from server.core.worker.devices import CellDevices
from server.settings.model import Settings
from server.storage.journal import FILTERS, Record, records
from tests.conftest import START, demo_stores
from tests.fakes import FakeCamera, FakeGlue, FakeRobot
from tests.serving import admin_headers, serve


@pytest.fixture
async def served(fast_settings: Settings) -> AsyncIterator[tuple[Cell, httpx.AsyncClient]]:
    """The cell (for its journal) and a client of its server."""
    settings = fast_settings.model_copy(
        update={
            "auto_recovery_enabled": True,
            "error_recovery_attempts": 1,
            "error_recovery_delay": 0.01,
        }
    )
    demo_stores(settings.data_path)
    cell = Cell(settings, devices=CellDevices(FakeRobot(speed_factor=50), FakeGlue(), FakeCamera()))
    async with (
        serve(cell) as url,
        httpx.AsyncClient(
            base_url=url, timeout=10, headers=admin_headers(settings.data_path)
        ) as client,
    ):
        await until_state(client, "IDLE")
        yield cell, client


@pytest.fixture
def api(served: tuple[Cell, httpx.AsyncClient]) -> httpx.AsyncClient:
    return served[1]


async def until_state(client: httpx.AsyncClient, state: str) -> None:
    async with asyncio.timeout(15):
        while (await client.get("/state")).json()["state"] != state:
            await asyncio.sleep(0.01)


async def a_shift(api: httpx.AsyncClient) -> dict[str, str]:
    """One sprayed part, one refused command, one e-stop, one failed calibration."""
    started = (await api.post("/start", json=START)).json()["event_id"]
    refused = (await api.post("/calibrate-robot")).json()["event_id"]
    await until_state(api, "IDLE")
    await api.post("/estop", json={"reason": "shift test"})
    await api.post("/reset")
    await until_state(api, "IDLE")
    await api.post("/calibrate-robot")  # no calibration possible with a blank camera frame
    await until_state(api, "ERROR")
    return {"started": started, "refused": refused}


async def test_history_operations_errors_events_with_filters_and_paging(api) -> None:
    ids = await a_shift(api)
    history = (await api.get("/history", params={"new_state": "ERROR"})).json()
    assert history["total"] == 2 and all(t["new_state"] == "ERROR" for t in history["transitions"])
    page = (await api.get("/history", params={"limit": 2, "offset": 1})).json()
    assert len(page["transitions"]) == 2 and page["total"] >= 6
    operations = (await api.get("/operations", params={"kind": "trajectory"})).json()
    assert operations["operations"][0]["outcome"] == "completed"
    assert operations["operations"][0]["workpieces"] == 1
    calibration = (await api.get("/operations", params={"kind": "calibrate_robot"})).json()
    assert calibration["operations"][0]["outcome"] == "failed"
    errors = (await api.get("/errors")).json()["errors"]
    assert {e["code"] for e in errors} >= {"EMERGENCY_STOP"}
    assert all(e["classification"] in ("critical", "recoverable", "warning") for e in errors)
    refused = (await api.get("/events", params={"outcome": "refused"})).json()["events"]
    assert ids["refused"] in {e["id"] for e in refused}
    accepted = (await api.get("/events", params={"type": "START_REQUESTED"})).json()["events"]
    assert accepted[0]["id"] == ids["started"] and accepted[0]["data"] == START
    bad = await api.get("/history", params={"limit": 0})
    assert bad.status_code == 422 and "limit" in bad.json()["detail"]


def test_the_routes_take_each_tables_declared_filters_documented() -> None:
    paths = generate()["paths"]
    for path, table, _, _ in analytics.TABLE_ROUTES:
        parameters = paths[path]["get"]["parameters"]
        filters = [f for f in FILTERS[table] if f.on_json_route]
        assert [p["name"] for p in parameters] == [
            "since",
            "until",
            *(f.column for f in filters),
            "limit",
            "offset",
        ]
        for parameter, declared in zip(parameters[2:-2], filters, strict=True):
            assert parameter["description"] == declared.meaning
            if declared.values:  # a closed set: one of them, as openapi.json says
                assert parameter["schema"]["anyOf"][0]["enum"] == list(declared.values)
            else:
                assert parameter["schema"]["anyOf"][0]["pattern"] == analytics.TEXT_PATTERN
    for table in analytics.EXPORT_TABLES:  # each table's CSV takes exactly its own filters
        exported = [p["name"] for p in paths[f"/export/{table}.csv"]["get"]["parameters"]]
        assert exported == ["since", "until", *(f.column for f in FILTERS[table])]


async def test_csv_export(api) -> None:
    await a_shift(api)
    response = await api.get("/export/transitions.csv")
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(response.text)))
    assert rows[0]["old_state"] == "INITIALIZING" and rows[0]["new_state"] == "IDLE"
    assert {"seq", "time", "event", "event_id", "time_in_old_state"} <= set(rows[0])
    disposition = response.headers["content-disposition"]
    assert disposition.startswith('attachment; filename="transitions-')
    assert disposition.endswith('.csv"')
    assert (await api.get("/export/secrets.csv")).status_code == 404


async def test_csv_export_takes_the_tables_filters(api) -> None:
    ids = await a_shift(api)
    refused = await api.get("/export/events.csv", params={"outcome": "refused"})
    rows = list(csv.DictReader(io.StringIO(refused.text)))
    assert ids["refused"] in {r["id"] for r in rows}
    assert rows and {r["outcome"] for r in rows} == {"refused"}
    errored = await api.get("/export/transitions.csv", params={"new_state": "ERROR"})
    transitions = list(csv.DictReader(io.StringIO(errored.text)))
    assert len(transitions) == 2 and {t["new_state"] for t in transitions} == {"ERROR"}
    failed = await api.get(
        "/export/operations.csv", params={"kind": "calibrate_robot", "outcome": "failed"}
    )
    assert [r["kind"] for r in csv.DictReader(io.StringIO(failed.text))] == ["calibrate_robot"]


async def test_csv_export_refuses_a_bad_filter_naming_it(api) -> None:
    bad = await api.get("/export/events.csv", params={"outcome": "refused'; --"})
    assert bad.status_code == 422
    assert [e["field"] for e in bad.json()["errors"]] == ["query.outcome"]
    # A column of another table: refused, not ignored (the file would hold more than asked).
    misplaced = await api.get("/export/events.csv", params={"kind": "trajectory"})
    assert misplaced.status_code == 422
    assert [e["field"] for e in misplaced.json()["errors"]] == ["query.kind"]
    assert "it takes: outcome, since, source, state, type, until" in misplaced.json()["detail"]


async def test_csv_export_of_an_empty_table_is_its_header(api) -> None:
    response = await api.get("/export/recoveries.csv")
    assert response.status_code == 200
    assert response.text == "seq,time,run_id,error_code,attempt,succeeded\r\n"
    filtered = await api.get("/export/events.csv", params={"type": "NO_SUCH_EVENT"})
    assert filtered.text == "id,time,type,source,data,outcome,message,state\r\n"


def a_test_error(i: int, at: float) -> Record:
    return records.error(at, f"TEST_{'AB'[i % 2]}", f"row {i}", "test", "warning", f"e{i}", "IDLE")


async def test_csv_export_streams_every_row_in_pages_once_and_in_order(served, monkeypatch) -> None:
    cell, api = served
    journal = cell.journal
    assert journal is not None
    # 50 rows over 5 distinct times, written out of time order: ties cross page boundaries.
    written = journal.append([a_test_error(i, 1000.0 + i % 5) for i in range(50)])
    assert written is not None
    await written
    monkeypatch.setattr(analytics, "EXPORT_PAGE_ROWS", 7)
    loop_thread = threading.get_ident()
    readers: list[int] = []
    wrote_meanwhile: list[bool] = []
    read_page = journal.page_after

    def page_after(*args: Any, **kwargs: Any) -> Any:
        readers.append(threading.get_ident())
        rows, cursor = read_page(*args, **kwargs)
        if len(readers) == 1 and not wrote_meanwhile:
            # Rows committed while the export streams, before and after where it is.
            wrote_meanwhile.append(True)
            db = sqlite3.connect(journal.path)
            with db:
                for i, at in ((50, 1000.0), (51, 1004.0), (52, 1500.0)):
                    record = a_test_error(i, at)
                    db.execute(record.sql, record.params)
            db.close()
        return rows, cursor

    monkeypatch.setattr(journal, "page_after", page_after)

    response = await api.get("/export/errors.csv")
    assert response.status_code == 200
    rows = list(csv.DictReader(io.StringIO(response.text)))
    in_order = sorted(range(50), key=lambda i: (i % 5, i))
    assert [r["message"] for r in rows if r["component"] == "test"] == [
        f"row {i}" for i in in_order
    ]
    assert len({r["seq"] for r in rows}) == len(rows)
    assert len(readers) >= 50 // 7 + 1 and loop_thread not in readers  # paged, off the loop

    readers.clear()  # the same, filtered and bounded in time
    response = await api.get(
        "/export/errors.csv", params={"code": "TEST_A", "since": 1001, "until": 1004}
    )
    rows = list(csv.DictReader(io.StringIO(response.text)))
    expected = [i for i in in_order if i % 2 == 0 and 1 <= i % 5 < 4]
    assert [r["message"] for r in rows] == [f"row {i}" for i in expected]
    assert {r["code"] for r in rows} == {"TEST_A"}


async def test_kpis_over_the_shift(api) -> None:
    await a_shift(api)
    kpis = (await api.get("/kpis")).json()
    assert kpis["window"]["hours"] == pytest.approx(8.0)
    assert kpis["failures"] == 2
    assert kpis["workpieces_processed"] == 1
    assert kpis["time_in_state_s"]["EXECUTING_TRAJECTORY"] > 0
    assert 0 < kpis["oee"]["availability"] <= 1
    # The fake devices' run completed and was inspected, but a fake camera shows no bead:
    # one part, defective, and the quality factor says so.
    assert (kpis["quality"]["parts_good"], kpis["quality"]["parts_defective"]) == (0, 1)
    assert kpis["oee"]["quality"] == 0.0 and kpis["oee"]["oee"] == 0.0
    assert kpis["error_recovery_success_rate"] == 0.0  # the calibration retry failed too
    assert (await api.get("/kpis", params={"since": 10, "until": 5})).status_code == 422
    assert (await api.get("/kpis", params={"since": 0, "until": "inf"})).status_code == 422


async def test_recovery_attempts_are_journaled(api) -> None:
    await a_shift(api)
    rows = list(csv.DictReader(io.StringIO((await api.get("/export/recoveries.csv")).text)))
    # The blank frame shows no marker: retried once (error_recovery_attempts=1), in vain.
    assert [(r["error_code"], r["attempt"], r["succeeded"]) for r in rows] == [
        ("MARKER_NOT_FOUND", "1", "0")
    ]


async def test_prometheus_metrics(api) -> None:
    await a_shift(api)
    text = (await api.get("/metrics")).text
    assert 'glue_cell_state{state="ERROR"} 1.0' in text
    assert 'glue_cell_transitions_total{new_state="EXECUTING_TRAJECTORY",old_state="IDLE"}' in text
    for name in (
        "glue_cell_events_processed_total",
        "glue_cell_events_refused_total",
        "glue_cell_event_queue_depth",
        "glue_cell_event_processing_seconds_bucket",
        "glue_cell_api_request_seconds_bucket",
        "glue_cell_websocket_clients",
        'glue_cell_device_connected{device="robot"}',
        "glue_cell_operation_duration_seconds_bucket",
    ):
        assert name in text, name
