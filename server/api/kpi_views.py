"""The body of GET /kpis as pydantic models: what openapi.json states of the KPIs.

Why declared: the plant's reports and the HMI read these keys, and the
`quality` block holds figures a client must know may be null. The
dict comes from `server/views/kpis.py: compute_kpis`; each description says
what null means there (docs/kpis.md has the formulas).
"""

from __future__ import annotations

from pydantic import BaseModel, Field


class KpiWindowView(BaseModel):
    start: float = Field(description="Unix time, inclusive")
    end: float = Field(description="Unix time, exclusive")
    hours: float


class OeeView(BaseModel):
    availability: float | None = Field(description="(A - R) / A; null when A = 0")
    performance: float | None = Field(description="min(1, design cycle × runs done / X)")
    quality: float | None = Field(
        description="good parts / inspected parts; null when no part was inspected"
    )
    oee: float | None = Field(description="the product; null when a factor is")


class PrecisionView(BaseModel):
    mean: float | None = Field(description="mean of each part's mean deviation (mm)")
    p95: float | None = Field(
        description="nearest-rank 95th percentile of each part's p95 deviation (mm)"
    )


class QualityView(BaseModel):
    """The window's parts (one part = one spray run that ended), each with the verdict
    every path gives it, and what their inspections measured."""

    parts_good: int = Field(description="parts inspected and judged good")
    parts_defective: int = Field(
        description="parts judged defective, or whose run did not complete (not inspected)"
    )
    parts_not_inspected: int = Field(description="parts sprayed whole that nobody inspected")
    trajectory_precision_mm: PrecisionView = Field(
        description="the robot's sampled path against the planned spray segments"
    )
    dispensing_cv_percent: float | None = Field(
        description="mean of each part's flow coefficient of variation while spraying (%)"
    )
    vision_residual_mm: float | None = Field(
        description="mean residual of the calibration markers re-detected on each part's frame"
    )


class KpisView(BaseModel):
    """GET /kpis: the figures of docs/kpis.md over one window; a ratio or mean over
    nothing is null, never a made-up 0 % or 100 %."""

    window: KpiWindowView
    available_time_s: float
    operations_ended: int
    operations_completed: int
    operations_completed_per_hour: float
    average_execution_time_s: dict[str, float | None] = Field(
        description="per operation kind; null for a kind with no completed run"
    )
    utilization: float | None
    errors_counted: int
    error_rate_per_100_operations: float | None
    failures: int
    mtbf_s: float | None
    mttr_s: float | None
    recovery_attempts: int
    error_recovery_success_rate: float | None
    time_in_state_s: dict[str, float]
    workpieces_processed: int
    workpieces_failed: int
    oee: OeeView
    quality: QualityView
