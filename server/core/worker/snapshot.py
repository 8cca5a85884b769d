"""The state snapshot file: what the cell was doing, rewritten atomically.

Only the latest snapshot matters, so writes coalesce: a background thread
writes whatever is newest when it gets to it, and the worker never waits. A
change's snapshot is handed to that thread once the change's commit is
durable and its sender answered (`Recorder.answer_when_durable`), so its
write (a temporary file, an fsync, a rename) competes with neither; the
journal is therefore never behind the snapshot, and a restart takes the
journal's last transition when it is the newer of the two (`server/bootstrap/cell.py`,
`last_state`). The
file is also refreshed every persistence_interval seconds (its `saved_at` says
how fresh it is). At start a missing, truncated or corrupt file is logged,
kept aside for inspection, and the cell starts safely without it.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path
from typing import Any

from server.common.runtime import background_thread
from server.storage.files import write_json_atomic

log = logging.getLogger(__name__)


class SnapshotFile:
    """Latest-wins atomic writes of the state snapshot at `path`."""

    def __init__(self, path: Path, interval: float) -> None:
        self.path = path
        self.interval = interval
        self._latest: dict[str, Any] | None = None
        self._dirty = threading.Event()
        self._stopping = False
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    def load(self) -> dict[str, Any] | None:
        """The last snapshot, or None; a damaged file is kept aside, never fatal."""
        try:
            text = self.path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return None
        try:
            document = json.loads(text)
            if not isinstance(document, dict) or "state" not in document:
                raise ValueError("no state recorded")
            return document
        except ValueError as exc:
            aside = self.path.with_name(f"{self.path.name}.corrupt-{int(time.time())}")
            self.path.replace(aside)
            log.error(
                "state snapshot %s is damaged (%s); kept as %s, starting without it",
                self.path,
                exc,
                aside,
            )
            return None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._write_loop, name="state-snapshot", daemon=True)
        self._thread.start()

    @staticmethod
    def copy(snapshot: dict[str, Any]) -> dict[str, Any]:
        """A copy to save: plain JSON values, sharing none of the caller's dicts (it goes
        on changing them)."""
        copied: dict[str, Any] = json.loads(json.dumps(snapshot, default=str))
        return copied

    def save(self, copy: dict[str, Any]) -> None:
        """Write `copy` (made by `copy`) soon, in the writer thread."""
        with self._lock:
            self._latest = copy
        self._dirty.set()

    def stop(self) -> None:
        self._stopping = True
        self._dirty.set()
        if self._thread is not None:
            self._thread.join(timeout=10)

    def _write_loop(self) -> None:
        with background_thread():  # held back while an e-stop's frames are written
            self._write_latest()

    def _write_latest(self) -> None:
        while True:
            self._dirty.wait(timeout=self.interval)
            self._dirty.clear()
            with self._lock:
                latest = self._latest
            if latest is not None:
                try:
                    write_json_atomic(self.path, {**latest, "saved_at": time.time()})
                except Exception as exc:  # the writer must outlive any one bad write
                    log.error("could not write the state snapshot %s: %s", self.path, exc)
            if self._stopping:
                return
