"""What start-up does with the journal it finds: check it, and keep whatever is damaged.

The choice, for a cell that must keep working: journal damage never stops the
server (the e-stop and the cell work without a history) and is never silent.

- SQLite cannot read the file (PRAGMA quick_check fails, or a read does): the
  journal is set aside, `journal.db.corrupt-<time>` together with its `-wal`,
  `-shm` and `.last-commit` under the same name (SQLite opens a WAL only
  beside its own main file, so one without the other is lost), and a new
  journal is started.
- SQLite reads it but commits are missing or rows rewritten (`verify.py`): the
  readable journal is kept and goes on from its last readable commit; a copy
  of the files as found, `journal.db.damaged-<time>` (and `-wal`, ...), is kept
  first, since the lost transactions may still lie in the WAL past the
  damaged frame and SQLite overwrites them at the next commit (no room for
  the copy: logged, and the journal is kept all the same).
- SQLite reads it but the chain itself does not read (a commit's row
  rewritten into nonsense): said so, the journal kept and copied, and the
  chain started again after its highest commit.
- SQLite cannot open it at all (locked by another process, no permission, an
  I/O error): that is not damage, nothing is moved, and the error stops the
  start as any failure to open the journal does.

Either way each finding is a CRITICAL log line naming what is missing (which
commits, how many rows of which table) and where the files went; the journal
keeps the findings for /health for the life of the process, and the cell
records them in the journal's `errors` (code JOURNAL_DAMAGED), so they outlive
a restart. The check only reads, through a read-only connection, so nothing is
checkpointed or overwritten before the copy is made.
"""

from __future__ import annotations

import logging
import shutil
import sqlite3
import time
from dataclasses import dataclass, replace
from pathlib import Path

from server.storage.journal.commit_chain import GENESIS, LAST_COMMIT_SUFFIX, Head, LastCommitFile
from server.storage.journal.verify import WINDOW, Damage, verify

log = logging.getLogger(__name__)

# The files one journal lives in: the main file, SQLite's two, the chain's note.
COMPANIONS = ("", "-wal", "-shm", LAST_COMMIT_SUFFIX)


@dataclass(frozen=True, slots=True)
class Inspection:
    """Where the commit chain goes on, and what was found wrong (empty when nothing).

    `restarted`: the chain could not be read, so it starts again after `head`
    (an anchor the journal must note, as retention does, before it writes).
    """

    head: Head
    damage: list[Damage]
    restarted: bool = False


class Unreadable(sqlite3.DatabaseError):
    """SQLite's own check of the journal failed."""


def inspect(path: Path, last_commit: LastCommitFile, window: int | None = WINDOW) -> Inspection:
    """Check the journal at `path` before anything writes to it; keep what is damaged.

    Raises sqlite3.Error only when the journal cannot be opened at all (locked by
    another process, no permission, an I/O error): that is no damage to set aside.
    """
    found_at = time.time()
    damage: list[Damage] = []
    try:
        noted = last_commit.read()
    except (OSError, ValueError) as exc:
        noted = None
        damage.append(
            Damage(
                f"journal damaged: its last-commit record {last_commit.path.name} is "
                f"unreadable ({exc}): whether its last commits are all there cannot be told"
            )
        )
    restarted = False
    if not path.exists():
        head, found = GENESIS, _absent(noted)
    else:
        try:
            head, found = _read(path, noted, window)
        except sqlite3.DatabaseError as exc:
            if not _damaged(exc):
                raise
            aside = _move(path, "corrupt")
            found_aside = Damage(
                f"journal damaged: SQLite cannot read {path.name} ({exc}); set aside as "
                f"{aside.name} with its -wal and -shm, and a new journal started",
                kept_as=aside.name,
            )
            return _reported(Inspection(GENESIS, [found_aside]), found_at)
        except Exception as exc:  # SQLite reads it, the chain in it does not make sense
            head, restarted = _restart_point(path), True
            found = [
                Damage(
                    f"journal damaged: its commit chain is unreadable ({exc}); the journal is "
                    f"kept and its chain starts again after commit {head.seq}",
                    last_commit=head.seq,
                )
            ]
    damage += found
    if damage and path.exists():
        copy = _copy(path, "damaged")
        damage = [replace(d, kept_as=copy.name if copy else None) for d in damage]
    return _reported(Inspection(head, damage, restarted), found_at)


def _read(path: Path, noted: Head | None, window: int | None) -> tuple[Head, list[Damage]]:
    connection = _read_only(path)
    try:
        result = connection.execute("PRAGMA quick_check").fetchone()
        if result is None or result[0] != "ok":
            raise Unreadable(f"quick_check: {result}")
        verdict = verify(connection, noted, window=window)
    finally:
        connection.close()
    return verdict.head, verdict.damage


def _read_only(path: Path) -> sqlite3.Connection:
    return sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True)


def _damaged(exc: sqlite3.DatabaseError) -> bool:
    """The file itself is damaged (not merely locked, forbidden or on a failing read)."""
    codes = (sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB)
    return isinstance(exc, Unreadable) or getattr(exc, "sqlite_errorcode", None) in codes


def _restart_point(path: Path) -> Head:
    """Where a chain that cannot be read starts again: after its highest commit number."""
    connection = _read_only(path)
    try:
        found = connection.execute("SELECT MAX(seq) FROM commits").fetchone()
    finally:
        connection.close()
    return Head(int(found[0] or 0), time.time(), {}, "")


def _absent(noted: Head | None) -> list[Damage]:
    """No journal file, yet the last-commit record says commits were made."""
    if noted is None or noted.seq == 0:
        return []
    return [
        Damage(
            f"journal damaged: the journal file is gone, but its last-commit record names "
            f"commit {noted.seq}: commits 1 to {noted.seq} are missing",
            1,
            noted.seq,
            {t: n for t, n in sorted(noted.rows.items()) if n},
        )
    ]


def _reported(inspection: Inspection, found_at: float) -> Inspection:
    damage = [replace(d, found_at=found_at) for d in inspection.damage]
    for finding in damage:
        kept = ""
        if finding.kept_as and finding.kept_as not in finding.message:
            kept = f"; the files as found are kept as {finding.kept_as}"
        log.critical("%s%s", finding.message, kept)
    return replace(inspection, damage=damage)


def _free_name(path: Path, label: str) -> Path:
    stamp = int(time.time())
    for n in range(100):
        name = f"{path.name}.{label}-{stamp}" + (f"-{n}" if n else "")
        candidate = path.with_name(name)
        if not any(Path(f"{candidate}{suffix}").exists() for suffix in COMPANIONS):
            return candidate
    raise FileExistsError(f"no free name to keep {path} as {label}")


def _move(path: Path, label: str) -> Path:
    """Set the journal and its companions aside under one new name."""
    aside = _free_name(path, label)
    for suffix in COMPANIONS:
        source = Path(f"{path}{suffix}")
        if source.exists():
            source.replace(Path(f"{aside}{suffix}"))
    return aside


def _copy(path: Path, label: str) -> Path | None:
    """A copy of the journal and its companions as found (None, logged, when it fails:
    what was copied is removed, so a full disk is not left fuller)."""
    made: list[Path] = []
    try:
        copy = _free_name(path, label)
        for suffix in COMPANIONS:
            source = Path(f"{path}{suffix}")
            if source.exists():
                made.append(Path(f"{copy}{suffix}"))
                shutil.copy2(source, made[-1])
    except OSError as exc:
        for target in made:
            target.unlink(missing_ok=True)
        log.error("could not keep a copy of the damaged journal %s: %s", path, exc)
        return None
    return copy
