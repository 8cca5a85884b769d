"""The `StorageSettings` section of the settings. The data directory, the state snapshot
and the SQLite journal.
"""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar, Literal

from pydantic import Field

from server.settings.section import Section


class StorageSettings(Section):
    """The data directory, the state snapshot and the SQLite journal."""

    title: ClassVar[str] = "Persistence and the journal"

    data_path: Path = Field(Path("data"), description="where state, journal and tokens live")
    state_persistence: bool = Field(
        True, description="save the state snapshot, to tell an interrupted run after a restart"
    )
    persistence_file: str | None = Field(None, description="default <data>/state.json")
    persistence_interval: float = Field(
        30.0, ge=1, le=3600, description="seconds between saves of the state snapshot"
    )
    analytics_enabled: bool = Field(
        True, description="accepted, no effect: the journal is always written"
    )
    analytics_database: str | None = Field(None, description="default <data>/journal.db")
    analytics_retention_days: int = Field(
        90, ge=1, le=3650, description="days of journal rows kept"
    )
    journal_synchronous: Literal["OFF", "NORMAL", "FULL"] = Field(
        "FULL", description="SQLite synchronous level: FULL survives power loss"
    )

    def data_file(self, configured: str | None, default: str) -> Path:
        """A file under the data directory unless configured as an absolute path."""
        path = Path(configured) if configured else Path(default)
        return path if path.is_absolute() else self.data_path / path

    @property
    def journal_file(self) -> Path:
        """Where the journal is (analytics_database, by default under the data directory)."""
        return self.data_file(self.analytics_database, "journal.db")
