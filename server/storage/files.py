"""Crash-safe small files: write to a temporary sibling, fsync, then rename.

A reader (or a restart after power loss) sees either the old file or the new
one, never half of each.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

from server.storage.permissions import private_directory


def write_bytes_atomic(path: Path, data: bytes) -> None:
    """Replace `path` with `data` atomically (same directory, fsync, rename)."""
    private_directory(path.parent)
    # mkstemp makes the file 0600 (server/storage/permissions.py): the cell's user only.
    descriptor, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(descriptor, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def write_json_atomic(path: Path, document: Any) -> None:
    write_bytes_atomic(path, json.dumps(document, indent=2, ensure_ascii=False).encode("utf-8"))


def read_json(path: Path) -> Any | None:
    """The document at `path`, or None when there is none; a corrupt file raises ValueError."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(
            f"{path} is not valid JSON ({exc}); move it aside and recalibrate"
        ) from exc
