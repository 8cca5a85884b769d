"""The diagnostic bundle: one .tar.gz holding what a support engineer asks for first.

`GET /diagnostics` (maintenance role) builds it from the running server, with its
live /health; `glue-server diagnose FILE` builds it from the data directory
alone, so it works when the server does not start (the case where it is needed
most). Either way it holds:

    README.txt           what each file is, when and by what it was made
    version.json         the product's version and revision, Python, the platform
    settings.json        the settings in force, as GET /settings shows them (secrets
                         masked, webhook URLs cut to their host)
    health.json          the live /health (devices, worker, journal, links), or why not
    faults.json          the newest faults, each with its context and stack
    transitions.json     the newest state changes
    maintenance.json     the wear counters and each maintenance item (due, overdue), the
                         pot life and the glue level, as GET /maintenance answers, judged
                         from the journal's wear table (as of its last write)
    journal-check.txt    the journal's own check (as `python -m server.storage.journal.check`)
    logs/<name>.tail     the end of the log file, already redacted as it was written

No token, ticket or password goes in: the data directory's token files are not
read, and the log and settings carry no secret by construction (docs/security.md).
"""

from __future__ import annotations

import io
import json
import platform
import sqlite3
import sys
import tarfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from server.common.build import package_version, source_revision
from server.core.worker.care_rules import state_of
from server.settings.model import Settings
from server.storage.journal import TABLES, wear
from server.storage.journal.check import check

FAULTS_KEPT = 50
TRANSITIONS_KEPT = 200
LOG_TAIL_BYTES = 512 * 1024  # about a busy shift's lines; the whole file is the log's own


def collect(settings: Settings, health: Mapping[str, Any] | None, made_by: str) -> dict[str, bytes]:
    """The bundle's files by name. `health`: the live /health, or None when the server
    was not asked (the command line, which reads the data directory alone)."""
    now = time.time()
    journal = settings.journal_file
    files: dict[str, bytes] = {
        "version.json": _json(
            {
                "version": package_version(),
                "revision": source_revision(),
                "python": sys.version,
                "platform": platform.platform(),
            }
        ),
        "settings.json": _json(settings.model_dump(mode="json")),
        "health.json": _json(
            dict(health)
            if health is not None
            else {"not_asked": f"{made_by} reads the data directory; GET /diagnostics has it"}
        ),
    }
    if journal.is_file():
        files["faults.json"] = _json(_newest(journal, "errors", FAULTS_KEPT))
        files["transitions.json"] = _json(_newest(journal, "transitions", TRANSITIONS_KEPT))
        files["maintenance.json"] = _json(_maintenance(journal, settings, now))
        files["journal-check.txt"] = ("\n".join(check(journal)) + "\n").encode()
    else:
        files["journal-check.txt"] = f"no journal at {journal}\n".encode()
    log = settings.log_file
    if log.is_file():
        files[f"logs/{log.name}.tail"] = _tail(log, LOG_TAIL_BYTES)
    files["README.txt"] = _readme(made_by, now, sorted(files)).encode()
    return files


def archive(files: Mapping[str, bytes], name: str = "glue-cell-diagnostics") -> bytes:
    """The files as one gzip'd tar, under one directory `name`, each 0644."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        now = time.time()
        for path, data in files.items():
            info = tarfile.TarInfo(f"{name}/{path}")
            info.size, info.mtime, info.mode = len(data), now, 0o644
            tar.addfile(info, io.BytesIO(data))
    return buffer.getvalue()


def _newest(journal: Path, table: str, count: int) -> list[dict[str, Any]]:
    """The newest `count` rows of `table`, decoded as the API serves them; read-only, so
    it may run beside a server writing."""
    declared = TABLES[table]
    columns = ", ".join(declared.column_names)
    connection = sqlite3.connect(f"{journal.resolve().as_uri()}?mode=ro", uri=True)
    try:
        rows = connection.execute(
            f"SELECT {columns} FROM {table} ORDER BY seq DESC LIMIT ?", (count,)
        ).fetchall()
    except sqlite3.DatabaseError as exc:  # the journal check says more
        return [{"unreadable": str(exc)}]
    finally:
        connection.close()
    return [declared.decode(dict(zip(declared.column_names, row, strict=True))) for row in rows]


def _maintenance(journal: Path, settings: Settings, now: float) -> dict[str, Any]:
    """What GET /maintenance answers, from the wear totals the journal last kept (a running
    cell writes them every wear_persist_interval, at each run's end and at a clean stop),
    judged with the settings in force by the care meter's own rules."""
    try:
        values, written = wear.read(journal), wear.written_at(journal)
    except sqlite3.DatabaseError as exc:  # the journal check says more
        return {"unreadable": str(exc)}
    return {**state_of(values, settings, now), "as_of": written}


def _tail(path: Path, size: int) -> bytes:
    """The last `size` bytes of `path`, from the start of a line."""
    with path.open("rb") as file:
        file.seek(0, 2)
        end = file.tell()
        file.seek(max(0, end - size))
        data = file.read()
    if end > size and b"\n" in data:
        data = data[data.index(b"\n") + 1 :]
    return data


def _json(value: Any) -> bytes:
    return (json.dumps(value, indent=2, default=str) + "\n").encode()


def _readme(made_by: str, at: float, names: list[str]) -> str:
    when = time.strftime("%Y-%m-%d %H:%M:%S %z", time.localtime(at))
    listing = "\n".join(f"  {name}" for name in [*names, "README.txt"])
    return (
        f"Diagnostic bundle of a glue cell, made {when} by {made_by}.\n"
        "What each file holds: server/diagnostics/bundle.py. No token or password is in it.\n"
        f"\n{listing}\n"
    )
