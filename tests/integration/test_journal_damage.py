"""Journal damage found at start-up, on real SQLite files: what is missing or
rewritten is named, a journal SQLite cannot read is set aside whole (with its
-wal, -shm and last-commit record), and retention is never taken for damage.

A "crash image" is a copy of the journal's files taken while its writer still
has them open: what a disk holds after the process is killed.
"""

from __future__ import annotations

import asyncio
import sqlite3
import time
from pathlib import Path

import pytest

from bench import journal_verify
from bench.report import RESULTS_ENV
from server.storage.journal import SCHEMA, Journal, records
from server.storage.journal.check import main as check_main
from server.storage.journal.commit_chain import LastCommitFile
from server.storage.journal.verify import verify

FILES = ("", "-wal", "-shm", ".last-commit")


async def a_journal(path: Path, **options: object) -> Journal:
    journal = Journal(path, **options)  # type: ignore[arg-type]
    journal.open()
    journal.start(asyncio.get_running_loop())
    return journal


async def commit_events(journal: Journal, count: int, at: float | None = None) -> None:
    """`count` commits, each an event and its transition (as the worker writes them)."""
    for i in range(count):
        when = time.time() if at is None else at
        event_id = f"e{time.monotonic_ns()}-{i}"
        durable = journal.append(
            [
                records.event(event_id, when, "ESTOP", "test", {}, "accepted", "", "ERROR"),
                records.transition(
                    {
                        "timestamp": when,
                        "old_state": "IDLE",
                        "new_state": "ERROR",
                        "event": "ESTOP",
                        "event_id": event_id,
                        "time_in_old_state": 1.5,
                    }
                ),
            ]
        )
        assert durable is not None
        await durable


async def crash_image(journal: Journal, into: Path) -> Path:
    """The journal's files as a SIGKILL now would leave them, copied to `into`."""
    await journal.caught_up()
    return copy_files(journal.path, into)


def copy_files(journal: Path, into: Path) -> Path:
    into.mkdir()
    for suffix, content in files(journal).items():
        (into / f"{journal.name}{suffix}").write_bytes(content)
    return into / journal.name


def files(journal: Path) -> dict[str, bytes]:
    """The content of each of the journal's files that exists, by suffix."""
    found = {}
    for suffix in FILES:
        path = Path(f"{journal}{suffix}")
        if path.exists():
            found[suffix] = path.read_bytes()
    return found


def lose_wal(journal: Path) -> None:
    Path(f"{journal}-wal").unlink()


def count(path: Path, table: str) -> int:
    with sqlite3.connect(path) as connection:
        return int(connection.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])


async def test_a_journal_cut_short_names_the_commits_and_rows_lost(tmp_path) -> None:
    journal = await a_journal(tmp_path / "live" / "journal.db")
    await commit_events(journal, 5)
    journal.stop()  # the first five checkpointed into the main file
    journal = await a_journal(journal.path)
    await commit_events(journal, 3)  # these three live only in the WAL
    image = await crash_image(journal, tmp_path / "image")
    journal.stop()
    lose_wal(image)

    reopened = Journal(image)
    reopened.open()
    [damage] = reopened.damage
    assert (damage.first_commit, damage.last_commit) == (6, 8)
    assert damage.missing_rows == {"events": 3, "transitions": 3}
    assert "last 3 commits (6 to 8" in damage.message
    # The readable journal goes on from its last commit: the next start finds nothing.
    reopened.start(asyncio.get_running_loop())
    await commit_events(reopened, 1)
    reopened.stop()
    assert (await a_journal(image)).damage == []
    assert count(image, "events") == 6


async def test_a_journal_sqlite_cannot_read_is_set_aside_with_its_wal_and_shm(tmp_path) -> None:
    journal = await a_journal(tmp_path / "live" / "journal.db")
    await commit_events(journal, 3)
    image = await crash_image(journal, tmp_path / "image")
    journal.stop()
    with image.open("r+b") as handle:  # the header: "file is not a database"
        handle.write(b"\x00" * 16)
    as_found = files(image)

    reopened = Journal(image)
    reopened.open()
    [aside] = list(image.parent.glob("journal.db.corrupt-*[0-9]"))
    kept = files(aside)  # together, under one name, unchanged but for SQLite's WAL index
    assert kept.keys() == as_found.keys() == set(FILES)
    assert {s: kept[s] == as_found[s] for s in FILES if s != "-shm"} == dict.fromkeys(
        ("", "-wal", ".last-commit"), True
    )
    [damage] = reopened.damage
    assert damage.kept_as == aside.name
    assert "cannot read" in damage.message
    assert count(image, "events") == 0  # a new journal
    reopened.start(asyncio.get_running_loop())
    await commit_events(reopened, 1)
    reopened.stop()
    assert (await a_journal(image)).damage == []


async def test_a_row_rewritten_on_disk_is_found(tmp_path) -> None:
    journal = await a_journal(tmp_path / "journal.db")
    await commit_events(journal, 2)
    written = journal.append(
        [records.error(time.time(), "ALARM", "valve closed at 12:00", "glue", "critical", "", "")]
    )
    assert written is not None
    await written
    await commit_events(journal, 2)
    journal.stop()  # everything checkpointed into the main file
    content = journal.path.read_bytes()
    assert content.count(b"valve closed at 12:00") == 1
    journal.path.write_bytes(content.replace(b"at 12:00", b"at 13:00"))
    with sqlite3.connect(journal.path) as connection:  # SQLite itself sees nothing wrong
        assert connection.execute("PRAGMA quick_check").fetchone()[0] == "ok"

    reopened = Journal(journal.path)
    reopened.open()
    [damage] = reopened.damage
    assert (damage.first_commit, damage.last_commit) == (3, 3)
    assert "errors" in damage.message and "rewritten" in damage.message
    assert damage.kept_as and (journal.path.parent / damage.kept_as).is_file()


async def test_a_commit_row_rewritten_on_disk_is_found(tmp_path) -> None:
    journal = await a_journal(tmp_path / "journal.db")
    await commit_events(journal, 4)
    journal.stop()
    with sqlite3.connect(journal.path) as connection:
        connection.execute("UPDATE commits SET rows = 'not counts' WHERE seq = 2")

    reopened = Journal(journal.path)
    reopened.open()
    [damage] = reopened.damage
    assert (damage.first_commit, damage.last_commit) == (2, 2)
    assert "rewritten" in damage.message


async def test_commits_and_rows_missing_in_between_are_named(tmp_path) -> None:
    journal = await a_journal(tmp_path / "journal.db")
    await commit_events(journal, 6)
    journal.stop()
    with sqlite3.connect(journal.path) as connection:  # as if their pages were lost
        connection.execute("DELETE FROM commits WHERE seq IN (2, 3)")
        connection.execute("DELETE FROM events WHERE commit_seq IN (2, 3)")
        connection.execute("DELETE FROM transitions WHERE commit_seq IN (2, 3, 5)")

    reopened = Journal(journal.path)
    reopened.open()
    gap, rows = reopened.damage
    assert (gap.first_commit, gap.last_commit) == (2, 3)
    assert gap.missing_rows == {"events": 2, "transitions": 2}
    assert "commits 2 to 3 of 6 are missing" in gap.message
    assert (rows.first_commit, rows.last_commit, rows.missing_rows) == (5, 5, {"transitions": 1})


async def test_rows_missing_before_the_digested_window_are_counted(tmp_path) -> None:
    journal = await a_journal(tmp_path / "journal.db")
    await commit_events(journal, 5)
    journal.stop()
    with sqlite3.connect(journal.path) as connection:
        connection.execute("DELETE FROM transitions WHERE commit_seq = 1")
    with sqlite3.connect(journal.path) as connection:
        noted = LastCommitFile(journal.path).read()
        assert verify(connection, noted, window=2).damage[0].missing_rows == {"transitions": 1}
        full = verify(connection, noted, window=None).damage
    assert [(d.first_commit, d.last_commit) for d in full] == [(1, 1)]


async def test_a_commit_chain_that_does_not_read_is_started_again(tmp_path) -> None:
    journal = await a_journal(tmp_path / "journal.db")
    await commit_events(journal, 3)
    journal.stop()
    with sqlite3.connect(journal.path) as connection:
        connection.execute("UPDATE commits SET rows = 'not counts' WHERE seq = 3")

    journal = await a_journal(journal.path)  # starts all the same
    [damage] = journal.damage
    assert "commit chain is unreadable" in damage.message and damage.last_commit == 3
    await commit_events(journal, 2)
    journal.stop()
    assert (await a_journal(journal.path)).damage == []
    assert count(journal.path, "events") == 5


async def test_retention_is_not_damage(tmp_path) -> None:
    journal = await a_journal(tmp_path / "journal.db", retention_days=1)
    old = time.time() - 3 * 86_400
    await commit_events(journal, 3, at=old)
    await commit_events(journal, 2)
    # A row older than the cutoff in a commit made now (a clock set back): it goes too.
    written = journal.append([records.error(old, "ALARM", "old", "glue", "critical", "", "")])
    assert written is not None
    await written
    await commit_events(journal, 2)
    journal.stop()

    journal = await a_journal(journal.path, retention_days=1)  # retention runs at open
    assert journal.damage == []
    assert count(journal.path, "events") == 4 and count(journal.path, "errors") == 0
    await commit_events(journal, 1)
    journal.stop()
    assert (await a_journal(journal.path, retention_days=1)).damage == []


async def test_a_journal_from_before_the_chain_is_taken_as_it_is(tmp_path) -> None:
    path = tmp_path / "journal.db"
    with sqlite3.connect(path) as connection:  # the tables as they were, rows and all
        connection.execute("PRAGMA journal_mode=WAL")
        connection.executescript(SCHEMA)
        connection.executescript("DROP TABLE commits; DROP TABLE journal_meta;")
        record = records.event("old", time.time(), "X", "test", {}, "accepted", "", "IDLE")
        connection.execute(record.sql, record.params)
    journal = await a_journal(path)
    assert journal.damage == []
    await commit_events(journal, 2)
    journal.stop()
    assert (await a_journal(path)).damage == []
    assert count(path, "events") == 3


@pytest.mark.parametrize("content", [b"", b'{"seq": 3', b"\xff\xfe"])
async def test_an_unreadable_last_commit_record_is_damage(tmp_path, content: bytes) -> None:
    journal = await a_journal(tmp_path / "journal.db")
    await commit_events(journal, 2)
    journal.stop()
    LastCommitFile(journal.path).path.write_bytes(content)
    journal.open()
    [damage] = journal.damage
    assert "last-commit record" in damage.message and "unreadable" in damage.message


async def test_a_journal_file_gone_with_its_record_left_is_damage(tmp_path) -> None:
    journal = await a_journal(tmp_path / "journal.db")
    await commit_events(journal, 2)
    journal.stop()
    journal.path.unlink()
    journal.open()
    [damage] = journal.damage
    assert (damage.first_commit, damage.last_commit) == (1, 2)
    assert damage.missing_rows == {"events": 2, "transitions": 2}


async def test_the_full_check_names_the_damage_from_the_command_line(tmp_path, capsys) -> None:
    journal = await a_journal(tmp_path / "journal.db")
    await commit_events(journal, 3)
    journal.stop()
    assert check_main([str(journal.path)]) == 0
    assert capsys.readouterr().out.startswith("ok: commits up to 3, 3 digested again")
    with sqlite3.connect(journal.path) as connection:
        connection.execute("UPDATE transitions SET new_state = 'IDLE' WHERE commit_seq = 2")
    assert check_main([str(journal.path)]) == 1
    assert "the rows of commit 2 in events, transitions" in capsys.readouterr().out


def test_the_check_benchmark_builds_a_sound_journal(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv(RESULTS_ENV, str(tmp_path))
    rows = journal_verify.main(["--rows", "3000"])
    assert [row["commits_digested"] for row in rows] == [0, 1000, 1000]
