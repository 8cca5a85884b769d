"""The `WatchSettings` section of the settings. The cell watching itself: its memory
against the specification's limit, the data directory's free space, device round trips,
the error rate, and the control charts of each part's quality figures
(docs/operations-guide.md, "Monitoring"; docs/quality.md, "Trends").
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field, field_validator

from server.common.values import BYTE_SIZE_ACCEPTS, byte_size
from server.settings.section import Section


class WatchSettings(Section):
    """The cell watching itself, and the quality trends of its parts."""

    title: ClassVar[str] = "Monitoring and trends"

    memory_limit: str | None = Field(
        "512MB",
        description="the memory the server may use (its resident memory; the image process is "
        "shown beside it in GET /health): a warning at memory_warning_percent of it, an alert "
        "at all of it; the cell runs on either way; unset: not watched",
        json_schema_extra={"accepts": f"{BYTE_SIZE_ACCEPTS}, at least 1MB, or unset"},
    )
    memory_warning_percent: float = Field(
        80.0, ge=1, le=100, description="share of memory_limit that raises the warning"
    )
    free_space_warning: str = Field(
        "500MB",
        description="free space on the data directory's disk below which a warning is "
        "raised, before the journal cannot write",
        json_schema_extra={"accepts": BYTE_SIZE_ACCEPTS},
    )
    watch_interval_s: float = Field(
        5.0,
        ge=0.05,
        le=3600,
        description="seconds between two looks at the cell's own CPU, memory, open files, "
        "threads, free space and device round trips",
    )
    loop_lag_interval_s: float = Field(
        0.25,
        ge=0.01,
        le=60,
        description="seconds the event-loop lag sampler sleeps; the lag is how late it wakes",
    )
    rtt_window_samples: int = Field(
        60,
        ge=5,
        le=10000,
        description="round trips per device in a window (one per watch_interval_s); the first "
        "full window is the baseline, the latest one is compared with it",
    )
    rtt_degraded_factor: float = Field(
        3.0,
        ge=1.1,
        le=1000,
        description="a device's link is degrading when its latest window's p95 round trip is "
        "this many times the baseline's (and rtt_degraded_min_ms over it)",
    )
    rtt_degraded_min_ms: float = Field(
        20.0,
        ge=0,
        le=60000,
        description="the least rise of the p95 round trip over the baseline that is warned of, "
        "so a link of a fraction of a millisecond is not warned of for jitter",
    )
    error_rate_window_operations: int = Field(
        100, ge=1, le=100000, description="operations in the error rate's window (the latest)"
    )
    error_rate_alert_per_100: float = Field(
        10.0,
        ge=0,
        le=100,
        description="failed operations per 100 in the window above which an alert is raised",
    )
    trend_baseline_parts: int = Field(
        25,
        ge=5,
        le=10000,
        description="good parts whose figures set each control chart's centre line and limits",
    )
    trend_min_parts: int = Field(
        8,
        ge=3,
        le=10000,
        description="good parts needed before a control chart is judged at all",
    )
    trend_run_length: int = Field(
        8,
        ge=3,
        le=100,
        description="parts in a row on one side of the centre line that are a drift (8: a "
        "steady cell has such a run by chance about once in 128 parts; 7, once in 64)",
    )
    trend_sigma: float = Field(
        3.0, ge=1, le=10, description="a part this many standard deviations out is a drift"
    )

    @field_validator("memory_limit")
    @classmethod
    def _a_memory_size(cls, value: str | None) -> str | None:
        if value is not None and byte_size(value) < 1024**2:
            raise ValueError(f"{value!r} is below 1MB")
        return value

    @field_validator("free_space_warning")
    @classmethod
    def _a_free_space(cls, value: str) -> str:
        byte_size(value)
        return value
