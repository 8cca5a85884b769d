"""A journal damaged while the server was down is never taken silently.

SQLite drops every WAL frame from the first one whose checksum fails, so 64
bytes overwritten in `journal.db-wal` after a SIGKILL show up as rows that are
simply not there. The journal's running commit sequence, chained digest and
last-commit record let the next start see the loss: it says so on a CRITICAL
log line, in /health (`journal.damage`) and in the journal's own `errors`, and
the cell keeps working on the journal SQLite can still read.
"""

from __future__ import annotations

import shutil
import signal
import sqlite3
import time
from pathlib import Path

import httpx

from tests.processes import FAST_DEVICES, server_process
from tests.serving import admin_client, free_port

WAL_FRAME = 24 + 4096  # frame header + one page (the journal's page size)
WAL_HEADER = 32


def wait_for_state(client: httpx.Client, state: str) -> None:
    # A hang guard, not a measure: a restart that checks a damaged journal on a CI machine
    # shared with other work took over 30 s once.
    deadline = time.monotonic() + 180
    while (now := client.get("/state").json()["state"]) != state:
        assert time.monotonic() < deadline, f"the cell did not reach {state} (it is {now})"
        time.sleep(0.02)


def rows_sqlite_still_reads(data: Path, table: str, scratch: Path) -> int:
    """How many rows of `table` SQLite finds in a copy of the journal as it lies on disk."""
    scratch.mkdir()
    for name in ("journal.db", "journal.db-wal"):
        shutil.copy(data / name, scratch / name)
    with sqlite3.connect(scratch / "journal.db") as connection:
        return int(connection.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])


def test_a_wal_damaged_after_a_kill_is_reported_and_the_cell_still_works(tmp_path: Path) -> None:
    data = tmp_path / "cell"
    data.mkdir()
    port = free_port()
    with server_process(port, data, FAST_DEVICES) as server:
        client = admin_client(port, data)
        wait_for_state(client, "IDLE")
        for _ in range(6):
            assert client.post("/estop").status_code == 202
            assert client.post("/reset").status_code == 202
            wait_for_state(client, "IDLE")
        written = client.get("/history", params={"limit": 1}).json()["total"]
        server.send_signal(signal.SIGKILL)
        server.wait(10)

    wal = data / "journal.db-wal"
    frames = (wal.stat().st_size - WAL_HEADER) // WAL_FRAME
    with wal.open("r+b") as handle:  # 64 bytes of a page in the middle of the WAL
        handle.seek(WAL_HEADER + (frames // 2) * WAL_FRAME + 24 + 100)
        handle.write(b"\xa5" * 64)
    damaged_wal = wal.read_bytes()
    readable = rows_sqlite_still_reads(data, "transitions", tmp_path / "copy")
    assert readable < written, "the damage cost no transition: the test proves nothing"

    port = free_port()
    with server_process(port, data, FAST_DEVICES) as server:
        client = admin_client(port, data)
        wait_for_state(client, "IDLE")
        damage = client.get("/health").json()["journal"]["damage"]
        assert len(damage) == 1, damage
        finding = damage[0]
        assert finding["missing_rows"]["transitions"] == written - readable
        first, last = finding["first_commit"], finding["last_commit"]
        named = f"({first}, made " if first == last else f"({first} to {last}, made until"
        assert named in finding["message"]
        # The readable journal is kept, with a copy of the damaged files beside it.
        assert finding["kept_as"] and (data / finding["kept_as"]).is_file()
        assert (data / f"{finding['kept_as']}-wal").read_bytes() == damaged_wal
        recorded = client.get("/errors", params={"code": "JOURNAL_DAMAGED"}).json()["errors"]
        assert [row["message"] for row in recorded] == [finding["message"]]
        # The cell still works.
        assert client.post("/estop").status_code == 202
        assert client.post("/reset").status_code == 202
        wait_for_state(client, "IDLE")
    log = (data / "server.log").read_text(encoding="utf-8")
    critical = [line for line in log.splitlines() if "[CRITICAL]" in line and "journal" in line]
    assert any(finding["message"] in line for line in critical), critical
