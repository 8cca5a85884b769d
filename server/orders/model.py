"""An order and its parts, and how a part counts: pure, so it is tested with data.

A part is one trajectory run of the order. Its verdict is the one every path
gives it (server/quality/part_verdict.py: `part_verdict`): good, defective
(inspected, or a run that did not complete: not inspected, with why), or
not_inspected (completed, nobody judged it: inspection off, or no space for
its image).

The order completes at its quantity of parts made whole and not found wrong:
good ones, and not inspected ones (nothing found them wrong and the operator
chose not to judge parts); `defect_limit` defective parts in a row stop it
(the nozzle or the calibration is wrong, and every further part would be
scrap).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from server.quality.part_verdict import DEFECTIVE, GOOD, NOT_INSPECTED, part_verdict
from server.storage.journal import PART_FIGURES

__all__ = ["DEFECTIVE", "GOOD", "NOT_INSPECTED", "Next", "Order", "OrderState", "Part"]


class OrderState(StrEnum):
    """Where an order is."""

    QUEUED = "queued"  # waits behind the active order
    RUNNING = "running"  # the cell works through it: each completed part starts the next
    HELD = "held"  # stopped (a fault, a stop, a cancelled run, the defect limit, a restart)
    COMPLETED = "completed"  # its quantity of good parts is made
    CLOSED = "closed"  # an operator ended it before that


ACTIVE_STATES = frozenset({OrderState.RUNNING, OrderState.HELD})
OPEN_STATES = ACTIVE_STATES | {OrderState.QUEUED}


class Next(StrEnum):
    """What follows a part."""

    CONTINUE = "continue"
    COMPLETE = "complete"
    DEFECT_LIMIT = "defect limit"


@dataclass(frozen=True, slots=True)
class Part:
    """One part of an order: its run and how it came out.

    `figures` holds its inspection's figures named by PART_FIGURES (the `order_parts`
    columns so marked in the journal's schema); one not measured is absent or None.
    """

    run_id: str
    started_at: float | None
    ended_at: float
    outcome: str  # how the run ended: completed, failed, cancelled, interrupted
    verdict: str  # good, defective or not_inspected (part_verdict)
    inspected: bool
    reasons: tuple[str, ...] = ()
    figures: Mapping[str, float | None] = field(default_factory=dict)

    @property
    def measured(self) -> dict[str, float | None]:
        """Every one of PART_FIGURES, in order: its value, None when not measured."""
        return {name: self.figures.get(name) for name in PART_FIGURES}

    def as_dict(self) -> dict[str, Any]:
        return {
            "run_id": self.run_id,
            "started_at": self.started_at,
            "ended_at": self.ended_at,
            "outcome": self.outcome,
            "verdict": self.verdict,
            "inspected": self.inspected,
            "reasons": list(self.reasons),
            **self.measured,
        }


def _number(value: Any) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


def part_of_run(
    run_id: str,
    outcome: str,
    started_at: float | None,
    ended_at: float,
    result: dict[str, Any] | None,
    error: str | None,
) -> Part:
    """The part a run made, judged by `part_verdict` from how it ended and its result."""
    judged = part_verdict(outcome, result, error)
    inspection = (result or {}).get("inspection") if judged.inspected else None
    figures = (
        {name: _number(inspection.get(name)) for name in PART_FIGURES}
        if isinstance(inspection, dict)
        else {}
    )
    return Part(
        run_id,
        started_at,
        ended_at,
        outcome,
        judged.verdict,
        judged.inspected,
        judged.reasons,
        figures,
    )


@dataclass(slots=True)
class Order:
    """N good parts of one workpiece; its parts in the order they were made."""

    order_id: str
    workpiece_id: str
    quantity: int
    defect_limit: int  # the setting when the order was made: its rule does not change midway
    created_at: float
    created_by: str
    state: OrderState = OrderState.QUEUED
    updated_at: float = 0.0
    reason: str | None = None  # why it is held, closed or completed
    parts: list[Part] = field(default_factory=list)
    # The creating client's Idempotency-Key: a retry with it gets this order, not a new one.
    idempotency_key: str | None = None

    @property
    def good(self) -> int:
        return sum(1 for p in self.parts if p.verdict == GOOD)

    @property
    def not_inspected(self) -> int:
        return sum(1 for p in self.parts if p.verdict == NOT_INSPECTED)

    @property
    def counted(self) -> int:
        """The parts that count toward the quantity: good ones and ones nobody judged."""
        return self.good + self.not_inspected

    @property
    def defective(self) -> int:
        return sum(1 for p in self.parts if p.verdict == DEFECTIVE)

    @property
    def defects_in_row(self) -> int:
        """Defective parts since the last good one."""
        count = 0
        for part in reversed(self.parts):
            if part.verdict != DEFECTIVE:
                break
            count += 1
        return count

    def count(self, part: Part) -> Next:
        """Add `part` and say what follows it."""
        self.parts.append(part)
        if self.counted >= self.quantity:
            return Next.COMPLETE
        if self.defects_in_row >= self.defect_limit:
            return Next.DEFECT_LIMIT
        return Next.CONTINUE

    def completed_reason(self) -> str:
        """Why the order completed: its parts counted toward the quantity, by verdict."""
        unjudged = f", {self.not_inspected} not inspected" if self.not_inspected else ""
        return f"{self.counted} parts made: {self.good} good{unjudged}"

    def defect_limit_reason(self) -> str:
        """The stop reason at the defect limit: what happened and what to check."""
        last = self.parts[-1] if self.parts else None
        found = "; ".join(last.reasons) if last and last.reasons else "no reason recorded"
        return (
            f"order {self.order_id}: {self.defects_in_row} defective parts in a row "
            f"(limit {self.defect_limit}); last part (run {last.run_id if last else '-'}): "
            f"{found}. Check the nozzle (clogged or worn: flow against setpoint), the glue "
            "supply and pressure, and the calibration (camera or table moved: recalibrate) "
            "before resetting the cell and resuming the order"
        )

    def as_dict(self) -> dict[str, Any]:
        return {
            "order_id": self.order_id,
            "workpiece_id": self.workpiece_id,
            "quantity": self.quantity,
            "defect_limit": self.defect_limit,
            "state": self.state.value,
            "reason": self.reason,
            "good": self.good,
            "defective": self.defective,
            "not_inspected": self.not_inspected,
            "counted": self.counted,
            "defects_in_row": self.defects_in_row,
            "parts_made": len(self.parts),
            "created_at": self.created_at,
            "created_by": self.created_by,
            "updated_at": self.updated_at,
        }
