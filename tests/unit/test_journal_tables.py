"""Each journal table's declaration is what a fresh journal holds, and what the rest reads.

tables.py declares every table once (columns with their SQL and Python types, time
column, filters, sealing); the SQL that creates the file, the filters, the CSV
headers, the record builders and the order report are derived from it. These
tests open a real journal file and hold the declarations to the schema SQLite
reports, and the derived pieces to the declarations.
"""

from __future__ import annotations

import sqlite3
from dataclasses import fields
from pathlib import Path
from typing import Any

import pytest

from server.api.orders import PartView
from server.orders.model import Part
from server.orders.report import COLUMNS as REPORT_COLUMNS
from server.quality.csv_columns import INSPECTION_COLUMNS
from server.storage.journal import Journal, records
from server.storage.journal.declaration import Table
from server.storage.journal.schema import (
    COMMIT_SEQ,
    FILTERS,
    LATER_COLUMNS,
    PART_FIGURES,
    SEALED,
    TABLES,
)
from server.storage.journal.tables import ALL_TABLES

# The Python types a column's SQL type may be read back as.
PY_OF_SQL = {"TEXT": {str, dict, list}, "REAL": {float}, "INTEGER": {int, bool}}


@pytest.fixture
def connection(tmp_path: Path) -> sqlite3.Connection:
    """A fresh journal, opened as the server opens it, read with a plain connection."""
    path = tmp_path / "journal.db"
    Journal(path).open()
    return sqlite3.connect(path)


@pytest.mark.parametrize("table", ALL_TABLES, ids=lambda t: t.name)
def test_each_declared_table_is_the_table_a_fresh_journal_holds(
    connection: sqlite3.Connection, table: Table
) -> None:
    live = connection.execute(f"PRAGMA table_info({table.name})").fetchall()
    extra = (COMMIT_SEQ,) if table.sealed else ()
    assert [row[1] for row in live] == [*table.column_names, *extra]
    for (_, name, sql_type, notnull, default, pk), column in zip(live, table.columns, strict=False):
        assert sql_type == column.sql_type, name
        assert bool(notnull) == ("NOT NULL" in column.sql), name
        assert bool(pk) == ("PRIMARY KEY" in column.sql), name
        assert default == (column.sql.split("DEFAULT ")[1] if "DEFAULT" in column.sql else None)
        assert column.py in PY_OF_SQL[column.sql_type], name
        assert column.meaning, name
    live_indexes = {
        (row[0], row[1])
        for row in connection.execute(
            "SELECT name, tbl_name FROM sqlite_master WHERE type = 'index' AND sql IS NOT NULL"
            " AND tbl_name = ?",
            (table.name,),
        )
    }
    assert live_indexes == {(index, table.name) for index, _ in table.indexes}
    for index, column_name in table.indexes:
        [(_, _, indexed)] = connection.execute(f"PRAGMA index_info({index})").fetchall()
        assert indexed == column_name


def test_a_fresh_journal_holds_no_table_the_schema_does_not_declare(
    connection: sqlite3.Connection,
) -> None:
    names = {
        row[0] for row in connection.execute("SELECT name FROM sqlite_master WHERE type='table'")
    }
    assert names - {"sqlite_sequence"} == {t.name for t in ALL_TABLES}


def test_record_tables_have_a_time_column_and_later_columns_end_their_rows() -> None:
    for name, table in TABLES.items():
        assert table.time_column in table.column_names, name
    assert set(SEALED) == {name for name, t in TABLES.items() if t.sealed}
    for name, later in LATER_COLUMNS.items():
        # sealed_form drops a later column holding its default from the end of the row
        assert TABLES[name].column_names[-len(later) :] == tuple(c for c, _, _ in later)


def test_the_filters_and_the_csv_headers_derive_from_the_columns() -> None:
    for name, table in TABLES.items():
        filtered = [c for c in table.columns if c.filter is not None]
        assert [f.column for f in FILTERS[name]] == [c.name for c in filtered]
        assert [f.type for f in FILTERS[name]] == [c.py for c in filtered]
        assert [f.meaning for f in FILTERS[name]] == [c.meaning for c in filtered]
    assert INSPECTION_COLUMNS[:2] == ("verdict", "reasons")
    assert set(PART_FIGURES) <= set(INSPECTION_COLUMNS)


def test_an_order_part_is_its_rows_columns_in_the_report_and_its_view() -> None:
    part = Part("run-1", 1.0, 2.0, "completed", "good", True, (), {"glue_ml": 0.5})
    outcome = [f.name for f in fields(Part) if f.name not in ("figures",)]
    assert list(part.as_dict()) == [*outcome, *PART_FIGURES]
    assert list(PartView.model_fields) == ["part", *part.as_dict()]
    assert REPORT_COLUMNS[7 : 7 + len(PART_FIGURES)] == PART_FIGURES
    parts = TABLES["order_parts"].column_names
    assert parts[-len(PART_FIGURES) :] == PART_FIGURES


def _one_of_each() -> dict[str, list[records.Record]]:
    """A row from every record builder, by the table it writes."""
    return {
        "events": [records.event("e-1", 1.0, "START", "api:x", {"a": 1}, "accepted", "", "IDLE")],
        "transitions": [
            records.transition(
                {
                    "timestamp": 1.0,
                    "old_state": "IDLE",
                    "new_state": "RUNNING",
                    "event": "START",
                    "event_id": "e-1",
                    "time_in_old_state": 0.5,
                }
            )
        ],
        "operations": [
            records.operation_started("r-1", "trajectory", 1.0, {"workpiece_id": "w"}),
            records.operation_planned("r-1", 2),
            records.operation_progress("r-1", {"total": 2}),
            records.operation_ended("r-1", 2.0, "completed", {"parts": 2}, None, 2),
        ],
        "errors": [records.error(1.0, "E", "m", "robot", "critical", "e-1", "ERROR")],
        "recoveries": [records.recovery(1.0, "r-1", "E", 1, True)],
        "audit": [records.audit(1.0, "p", "a", "POST /x", "accepted", "d", count=3)],
        "webhook_deliveries": [
            records.webhook_delivery(
                1.0, "d-1", "h", "fault", 0.5, "delivered", [{"status": 200}], ""
            )
        ],
        "inspections": [records.inspection(1.0, "r-1", {"verdict": "good", "took_s": 1})],
        "orders": [
            records.order(
                order_id="o-1",
                created_at=1.0,
                workpiece_id="w",
                quantity=2,
                defect_limit=3,
                state="running",
                reason=None,
                created_by="p",
                updated_at=1.0,
            )
        ],
        "order_parts": [
            records.order_part(
                time=2.0,
                order_id="o-1",
                run_id="r-1",
                started_at=1.0,
                outcome="completed",
                verdict="good",
                inspected=True,
                reasons=["a"],
                **dict.fromkeys(PART_FIGURES, 0.25),
            )
        ],
        "run_samples": [
            records.run_sample(
                time=1.0,
                run_id="r-1",
                x_mm=1.5,
                y_mm=2.5,
                z_mm=3.5,
                pose_at=0.99,
                speed_mm_s=None,
                valve_open=True,
                flow_ml_min=12.0,
                pressure_psi=40.0,
                glue_at=0.98,
            )
        ],
        "reports": [
            records.report(
                time=2.0, kind="shift", window_start=0.0, window_end=1.0, document={"oee": None}
            )
        ],
    }


def test_every_record_builder_writes_a_row_that_reads_back_as_declared(tmp_path: Path) -> None:
    path = tmp_path / "journal.db"
    journal = Journal(path)
    journal.open()
    built = _one_of_each()
    assert set(built) == set(TABLES)
    connection = sqlite3.connect(path)
    with connection:
        for rows in built.values():
            for record in rows:
                connection.execute(record.sql, record.params)
    connection.close()
    for name, table in TABLES.items():
        [row] = journal.query(name)
        decoded: dict[str, Any] = table.decode(row)
        assert list(decoded) == list(table.column_names)
        for column in table.columns:
            value = decoded[column.name]
            if value is not None:
                assert isinstance(value, column.py), (name, column.name, value)
            else:
                assert column.nullable, (name, column.name)


def test_a_row_naming_an_undeclared_column_is_refused() -> None:
    with pytest.raises(ValueError, match="no column"):
        records.order(order_id="o-1", colour="red")
    with pytest.raises(ValueError, match="needs"):
        records.order(order_id="o-1")
