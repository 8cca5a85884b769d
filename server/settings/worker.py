"""The `WorkerSettings` section of the settings. The event queue, operation attempts and
what the worker keeps in memory.
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from server.settings.section import Section


class WorkerSettings(Section):
    """The event queue, operation attempts and what the worker keeps in memory."""

    title: ClassVar[str] = "The worker"

    event_queue_size: int = Field(
        1000,
        ge=1,
        le=1_000_000,
        description="requests waiting for the worker; more are refused (503)",
    )
    processing_timeout: float = Field(
        60.0, ge=0.1, le=3600, description="seconds one attempt of an operation may run"
    )
    max_concurrent_operations: int = Field(
        1, ge=1, le=64, description="accepted for compatibility; the cell runs one at a time"
    )
    history_size: int = Field(1000, ge=10, le=1_000_000, description="transitions kept in memory")
    error_recovery_attempts: int = Field(
        3, ge=0, le=100, description="retries of a recoverable fault, with auto_recovery_enabled"
    )
    error_recovery_delay: float = Field(
        2.0, ge=0, le=600, description="seconds before a retry, times the attempt's number"
    )
    auto_recovery_enabled: bool = Field(
        False, description="retry an operation that failed on a recoverable fault"
    )
    performance_monitoring: bool = Field(
        True, description="accepted, no effect: metrics are always kept (GET /metrics)"
    )
    metrics_collection_interval: float = Field(
        10.0, ge=0.1, le=3600, description="seconds; accepted, no effect (metrics read on demand)"
    )
    performance_history_size: int = Field(
        1000, ge=10, le=1_000_000, description="processing-time samples kept for statistics"
    )
