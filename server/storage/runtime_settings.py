"""The settings changed at runtime (PATCH /settings), kept in the data directory.

Why a file of its own: a change made at the panel is a deliberate, audited
decision about this cell; it must survive a restart instead of falling back
silently to the configured value. The file holds only the settings changed at
runtime, by name, and is written like every small file of the cell (temporary
sibling, fsync, rename; mode 0600: server/storage/files.py), so a crash leaves
either the old set of changes or the new one. Which names may be in it, and how
they are put in force at start-up, is decided above this layer
(server/api/runtime_settings.py, server/bootstrap/cell.py).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from server.storage.files import read_json, write_json_atomic

FILE_NAME = "runtime-settings.json"


class RuntimeSettingsStore:
    """`runtime-settings.json` under the data directory: {setting name: value}."""

    def __init__(self, data_path: Path) -> None:
        self.path = Path(data_path) / FILE_NAME

    def load(self) -> dict[str, Any]:
        """The saved changes; {} when there are none. A file that is not a JSON object
        raises ValueError naming it (start-up says so and goes on without it)."""
        document = read_json(self.path)
        if document is None:
            return {}
        if not isinstance(document, dict):
            raise ValueError(f"{self.path} must hold a JSON object of settings")
        return document

    def save(self, values: dict[str, Any]) -> None:
        """Replace the saved changes with `values` (atomically; OSError if the disk refuses)."""
        write_json_atomic(self.path, dict(sorted(values.items())))
