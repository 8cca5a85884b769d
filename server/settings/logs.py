"""The `LogSettings` section of the settings. The log: its level, its file and how the file
is rotated.
"""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import AliasChoices, Field, field_validator

from server.common.values import BYTE_SIZE_ACCEPTS, byte_size
from server.settings.section import Section


class LogSettings(Section):
    """The log: its level, its file and how the file is rotated."""

    title: ClassVar[str] = "Logging"

    logging_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field(
        "INFO",
        validation_alias=AliasChoices("logging_level", "GLUE_APP_LOG_LEVEL"),
        description="least severity logged, on the console and in the log file",
    )
    log_file_path: str | None = Field(None, description="default <data>/logs/glue_cell.log")
    log_rotation_size: str = Field(
        "10MB",
        description="the log file is rotated at this size (a number and KB, MB or GB)",
        json_schema_extra={"accepts": f"{BYTE_SIZE_ACCEPTS}, at least 1KB"},
    )
    log_retention_days: int = Field(30, ge=1, le=3650, description="days rotated logs are kept")

    @field_validator("log_rotation_size")
    @classmethod
    def _a_log_size(cls, value: str) -> str:
        """Checked here, with the other settings: the log's set-up reads it before the cell
        starts, and a bad size there was a traceback instead of one line."""
        if byte_size(value) < 1024:
            raise ValueError(f"{value!r} is below 1KB")
        return value
