"""The annotated image of each run's inspection, one JPEG per run under `inspections/`.

Written atomically (server/storage/files.py), so a backup (which copies the
data directory) takes whole images only. Only the newest `kept` are kept: a
cell spraying a part a minute would otherwise fill its disk with pictures
(about 0.2 MB each at 1920×1080); the inspection's figures stay in the
journal after its image is gone.

A disk that fills while an image is written is not the run's fault: `save` raises
`NoRoomForImage` (nothing is left behind), and the trajectory run completes with
its part recorded as not inspected (no space) rather than failing a sprayed part.
"""

from __future__ import annotations

import errno
import re
from pathlib import Path

from server.storage.files import write_bytes_atomic

DIRECTORY = "inspections"
_RUN_ID = re.compile(r"^[A-Za-z0-9_.:-]{1,64}$")
# What a write answers when the disk (or the process's file-size limit, or a quota) is full.
NO_ROOM = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})


class NoRoomForImage(OSError):
    """The image could not be written for want of space; nothing of it was left."""


class InspectionImages:
    def __init__(self, data_path: Path, kept: int = 1000) -> None:
        self.directory = data_path / DIRECTORY
        self.kept = kept

    def path(self, run_id: str) -> Path | None:
        """Where run `run_id`'s image is (None for a name that is no run id)."""
        if not _RUN_ID.match(run_id) or run_id.startswith("."):
            return None
        return self.directory / f"{run_id}.jpg"

    def save(self, run_id: str, jpeg: bytes) -> None:
        path = self.path(run_id)
        if path is None:
            raise ValueError(f"not a run id: {run_id!r}")
        try:
            write_bytes_atomic(path, jpeg)
        except OSError as exc:
            if exc.errno in NO_ROOM:
                raise NoRoomForImage(exc.errno, exc.strerror, str(path)) from exc
            raise
        self.prune()

    def read(self, run_id: str) -> bytes | None:
        path = self.path(run_id)
        if path is None:
            return None
        try:
            return path.read_bytes()
        except FileNotFoundError:
            return None

    def prune(self) -> None:
        """Delete the oldest images beyond `kept`."""
        images = sorted(self.directory.glob("*.jpg"), key=lambda p: p.stat().st_mtime)
        for old in images[: max(0, len(images) - self.kept)]:
            old.unlink(missing_ok=True)
