"""Files only for the cell: what the server keeps is readable by its own user alone.

The journal holds who did what from where, the tokens file their hashes,
`admin.token` a secret; none of it is anyone else's business on a shared
machine. The modes are set explicitly where each file or directory is made,
not left to the process umask, so they hold however the server is started
(`python -m server`, an embedding application, a test):

- directories the server makes (the data directory, `logs/`,
  `calibration/`, `workpieces/`): 0700 (`private_directory`);
- the journal: 0600 before SQLite first opens it (`private_file`); SQLite
  gives its `-wal` and `-shm` the database's own mode;
- files written atomically (snapshot, calibrations, library, tokens,
  `admin.token`): 0600, as `tempfile.mkstemp` makes them
  (server/storage/files.py);
- the log files: 0640 (server/bootstrap/logging_setup.py), so a log shipper in the
  service's group can read a log directory opened to it (`log_file_path`
  outside the data directory); they never hold a secret.

A data directory left looser by an older version or an installer is
tightened at every start, and the log says what changed
(`tighten_data_directory`).
"""

from __future__ import annotations

import logging
import os
import stat
from collections.abc import Iterable
from pathlib import Path

log = logging.getLogger(__name__)

DIRECTORY_MODE = 0o700
FILE_MODE = 0o600
LOG_FILE_MODE = 0o640
SHOWN_CHANGES = 8  # in the log line; the rest are counted


def private_directory(path: Path) -> Path:
    """Create `path` (and any missing parent) for the cell's user only; an existing one stays.

    Only `path` itself gets 0700: parents are created as mkdir does by
    default, since a parent may be shared (a volume mount, /var/lib).
    """
    if not path.is_dir():
        path.mkdir(parents=True, exist_ok=True)
        os.chmod(path, DIRECTORY_MODE)
    return path


def private_file(path: Path) -> None:
    """Make sure `path` exists with mode 0600, before another library creates it (SQLite)."""
    descriptor = os.open(path, os.O_RDWR | os.O_CREAT, FILE_MODE)
    try:
        os.fchmod(descriptor, FILE_MODE)
    finally:
        os.close(descriptor)


def _allowed(path: Path, mode: int, log_files: Iterable[Path]) -> int:
    if stat.S_ISDIR(mode):
        return DIRECTORY_MODE
    if any(str(path).startswith(str(log_file)) for log_file in log_files):
        return LOG_FILE_MODE  # the log and its rotations (glue_cell.log.1, ...)
    return FILE_MODE


def tighten_data_directory(data_path: Path, log_files: Iterable[Path] = ()) -> list[str]:
    """Create the data directory 0700, or take every looser permission off what it holds.

    Only permissions are ever removed (nothing is loosened, nothing changes
    owner); symbolic links are not followed. What changed is logged once, as a
    warning: someone may have relied on reading these files. Returns the
    changes ("journal.db 644 -> 600").
    """
    log_files = list(log_files)
    if not data_path.exists():
        private_directory(data_path)
        return []
    changes = []
    for path in [data_path, *sorted(data_path.rglob("*"))]:
        try:
            mode = path.lstat().st_mode
            if stat.S_ISLNK(mode):
                continue
            old = stat.S_IMODE(mode)
            new = old & _allowed(path, mode, log_files)
            if new != old:
                os.chmod(path, new)
                name = "." if path == data_path else str(path.relative_to(data_path))
                changes.append(f"{name} {old:o} -> {new:o}")
        except FileNotFoundError:
            continue  # a temporary file renamed meanwhile
        except PermissionError as exc:
            log.error("cannot tighten the permissions of %s: %s", path, exc)
    if changes:
        shown = "; ".join(changes[:SHOWN_CHANGES])
        more = f"; and {len(changes) - SHOWN_CHANGES} more" if len(changes) > SHOWN_CHANGES else ""
        log.warning(
            "tightened permissions under %s (only the cell's user may read it): %s%s",
            data_path,
            shown,
            more,
        )
    return changes
