"""The marker layout being taught, kept under `<data>/calibration/markers.json`.

Why a draft: a layout is taught one marker at a time (jog the tool over marker
N, record where it is), and a layout with some markers still missing or from
two different tables must never be what the robot calibration maps to. So each
taught or typed position goes into the draft, which survives a restart; only a
whole draft that passes the settings' own layout check (`Settings._marker_layout`)
is applied to `marker_positions_mm`. The applied layout is kept here too, so a
restart puts the taught layout back in force (`applied`).

Each change writes the file first (atomically, 0600 like every file under the
data directory) and only then changes memory: a disk that refuses the write
leaves the layout as it was.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from server.storage.files import read_json, write_json_atomic

log = logging.getLogger(__name__)

MARKERS = 9  # ArUco markers 0-8, as marker_positions_mm


@dataclass(frozen=True, slots=True)
class DraftMarker:
    """One marker's position in the draft: where, how it got there ("taught"/"typed"), when."""

    x_mm: float
    y_mm: float
    how: str
    at: float

    def as_dict(self) -> dict[str, Any]:
        return {"x_mm": self.x_mm, "y_mm": self.y_mm, "how": self.how, "at": self.at}


class MarkerLayoutStore:
    """The draft layout and the last applied one, on disk and in memory."""

    def __init__(self, data_path: Path) -> None:
        self.path = data_path / "calibration" / "markers.json"
        self.draft: list[DraftMarker | None] = [None] * MARKERS
        self.applied: list[tuple[float, float]] | None = None
        self.applied_at: float | None = None
        self._load()

    def _load(self) -> None:
        try:
            document = read_json(self.path)
            if document is None:
                return
            draft = [None if entry is None else DraftMarker(**entry) for entry in document["draft"]]
            applied = document.get("applied")
            if len(draft) != MARKERS or (applied is not None and len(applied) != MARKERS):
                raise ValueError(f"it must hold {MARKERS} markers")
        except (ValueError, KeyError, TypeError) as exc:
            aside = self.path.with_suffix(f".corrupt-{int(time.time())}")
            self.path.replace(aside)
            log.error("marker layout %s unreadable (%s); kept as %s", self.path, exc, aside)
            return
        self.draft = draft
        if applied is not None:
            self.applied = [(float(x), float(y)) for x, y in applied]
            self.applied_at = document.get("applied_at")

    def _document(
        self, draft: list[DraftMarker | None], applied: list[tuple[float, float]] | None
    ) -> dict[str, Any]:
        return {
            "draft": [None if m is None else m.as_dict() for m in draft],
            "applied": None if applied is None else [list(p) for p in applied],
            "applied_at": self.applied_at,
        }

    def set_marker(self, marker: int, x_mm: float, y_mm: float, how: str) -> DraftMarker:
        """Put marker `marker`'s position in the draft (file first, then memory)."""
        entry = DraftMarker(round(x_mm, 3), round(y_mm, 3), how, time.time())
        draft = list(self.draft)
        draft[marker] = entry
        write_json_atomic(self.path, self._document(draft, self.applied))
        self.draft = draft
        return entry

    def clear_draft(self) -> None:
        """Start the draft over (the applied layout stays)."""
        draft: list[DraftMarker | None] = [None] * MARKERS
        write_json_atomic(self.path, self._document(draft, self.applied))
        self.draft = draft

    def missing(self) -> list[int]:
        """The markers the draft has no position for yet."""
        return [i for i, entry in enumerate(self.draft) if entry is None]

    def draft_layout(self) -> list[tuple[float, float]]:
        """The draft as marker_positions_mm (call once `missing()` is empty)."""
        return [(m.x_mm, m.y_mm) for m in self.draft if m is not None]

    def record_applied(self, layout: list[tuple[float, float]]) -> None:
        """Keep `layout` as the one applied. The draft stays: re-teaching one marker that
        moved, then applying again, must not need the other eight taught anew."""
        previous = self.applied_at
        self.applied_at = time.time()
        try:
            write_json_atomic(self.path, self._document(self.draft, layout))
        except BaseException:
            self.applied_at = previous
            raise
        self.applied = list(layout)
