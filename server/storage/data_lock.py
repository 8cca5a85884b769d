"""One process at a time on a data directory: the server while it runs, or a restore.

Why a lock: two servers on one data directory would interleave two journals'
commits and overwrite each other's snapshot, and a restore that replaced the
files under a running server would be overwritten by its next commit, or
leave it writing into files no longer there. `glue-server` holds
`<data>/server.lock` for its whole life (an exclusive `flock`); a restore
takes the same lock, so it refuses to run while a server does, and a server
started during a restore refuses to start. The kernel drops the lock when its
process ends, however it ends (a crash, SIGKILL, a power cut leaves no stale
lock to clean up); the file itself stays, holding the last holder's pid for
the message.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

from server.storage.permissions import FILE_MODE

LOCK_NAME = "server.lock"


class DataDirectoryBusy(RuntimeError):
    """Another process (a server, or a restore) holds the data directory."""


class DataDirectoryLock:
    """The exclusive lock on a data directory; `acquire` raises DataDirectoryBusy."""

    def __init__(self, data_path: Path, holder: str) -> None:
        self.path = data_path / LOCK_NAME
        self.holder = holder  # "server" or "restore": said to whoever finds it held
        self._fd: int | None = None

    def acquire(self) -> DataDirectoryLock:
        descriptor = os.open(self.path, os.O_RDWR | os.O_CREAT, FILE_MODE)
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            busy = self._busy(descriptor)
            os.close(descriptor)
            raise busy from None
        os.ftruncate(descriptor, 0)
        os.pwrite(descriptor, f"{self.holder} pid {os.getpid()}\n".encode(), 0)
        self._fd = descriptor
        return self

    def ensure_free(self) -> None:
        """DataDirectoryBusy when another process holds the lock; the file is left as it
        was (no lock file: nobody holds it), so asking leaves no trace."""
        try:
            descriptor = os.open(self.path, os.O_RDONLY)
        except FileNotFoundError:
            return
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise self._busy(descriptor) from None
        finally:
            os.close(descriptor)  # drops the lock taken, if it was

    def _busy(self, descriptor: int) -> DataDirectoryBusy:
        held_by = os.pread(descriptor, 200, 0).decode("utf-8", "replace").strip()
        return DataDirectoryBusy(
            f"{self.path.parent} is in use ({held_by or 'by another process'}): "
            "stop the server first"
        )

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the last descriptor drops the flock
            self._fd = None

    def __enter__(self) -> DataDirectoryLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()
