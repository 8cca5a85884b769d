"""An order's counting and its defect limit, on inspection summaries as data."""

from __future__ import annotations

from typing import Any

from server.orders.model import DEFECTIVE, GOOD, NOT_INSPECTED, Next, Order, part_of_run
from server.orders.report import report_csv, report_of


def summary(verdict: str, *reasons: str, glue: float = 1.5) -> dict[str, Any]:
    return {
        "inspection": {
            "verdict": verdict,
            "reasons": list(reasons),
            "precision_mean_mm": 0.12,
            "precision_p95_mm": 0.3,
            "dispensing_cv_percent": 2.0,
            "glue_ml": glue,
            "vision_residual_mm": 0.1,
            "image": True,
        }
    }


def order(quantity: int = 3, limit: int = 2) -> Order:
    return Order("ord-00000001", "demo", quantity, limit, 0.0, "op")


def completed(n: int, result: dict[str, Any] | None) -> Any:
    return part_of_run(f"r{n}", "completed", float(n), n + 0.5, result, None)


def test_the_inspections_verdict_and_figures_make_the_part() -> None:
    gap = "segment 3: a gap of 14.2 mm without bead (at most 3.0 mm)"
    part = completed(1, summary("defective", gap, glue=0.8))
    assert (part.verdict, part.inspected, part.reasons) == (DEFECTIVE, True, (gap,))
    assert part.figures == {"precision_mean_mm": 0.12, "precision_p95_mm": 0.3, "glue_ml": 0.8}
    assert completed(2, summary("good")).verdict == GOOD


def test_a_completed_run_without_inspection_is_not_inspected_saying_why() -> None:
    part = completed(1, {"path_length_mm": 400.0})
    reasons = ("not inspected (inspection_enabled is off)",)
    assert (part.verdict, part.inspected, part.reasons) == (NOT_INSPECTED, False, reasons)


def test_a_part_whose_image_a_full_disk_refused_is_not_inspected_no_space() -> None:
    """The run completed (the part is sprayed whole) but its inspection could not be kept:
    it counts as the order's parts without inspection do, saying why."""
    part = completed(1, {"path_length_mm": 400.0, "not_inspected": "no space"})
    assert (part.verdict, part.inspected) == (NOT_INSPECTED, False)
    assert part.reasons == ("not inspected (no space)",)


def test_a_defect_the_inspection_found_stands_when_a_full_disk_refused_its_image() -> None:
    """The image is missing, the verdict is not: a part the inspection found defective is
    never counted good for want of space."""
    found = {"verdict": DEFECTIVE, "reasons": ["glue volume 144 % of the bead's need"]}
    result = {"path_length_mm": 400.0, "not_inspected": "no space", "inspection_found": found}
    part = completed(1, result)
    assert (part.verdict, part.inspected) == (DEFECTIVE, False)
    assert part.reasons == ("not inspected (no space)", "glue volume 144 % of the bead's need")


def test_a_failed_stopped_or_cancelled_run_is_a_defective_part_saying_why() -> None:
    failed = part_of_run("r1", "failed", 1.0, 2.0, None, "robot: link lost")
    cancelled = part_of_run("r2", "cancelled", 1.0, 2.0, None, None)
    stopped = part_of_run("r3", "failed", 1.0, 2.0, None, "EMERGENCY_STOP")
    assert (failed.verdict, failed.reasons) == (DEFECTIVE, ("run failed: robot: link lost",))
    assert (cancelled.verdict, cancelled.reasons) == (DEFECTIVE, ("run cancelled",))
    assert stopped.reasons == ("run stopped: emergency stop (STOP)",)
    assert not (failed.inspected or cancelled.inspected or stopped.inspected)


def test_parts_nobody_inspected_count_toward_the_quantity_not_as_good() -> None:
    o = order(quantity=2, limit=5)
    assert o.count(completed(1, None)) is Next.CONTINUE
    assert o.count(completed(2, summary("good"))) is Next.COMPLETE
    assert (o.good, o.not_inspected, o.counted, o.defective) == (1, 1, 2, 0)
    assert o.completed_reason() == "2 parts made: 1 good, 1 not inspected"
    assert o.as_dict()["not_inspected"] == 1 and o.as_dict()["counted"] == 2


def test_the_order_completes_at_its_quantity_of_good_parts_not_of_parts() -> None:
    o = order(quantity=2, limit=5)
    assert o.count(completed(1, summary("good"))) is Next.CONTINUE
    assert o.count(completed(2, summary("defective", "segment 1: too narrow"))) is Next.CONTINUE
    assert o.count(completed(3, summary("good"))) is Next.COMPLETE
    assert (o.good, o.defective, o.defects_in_row) == (2, 1, 0)


def test_the_defect_limit_counts_defective_parts_in_a_row_only() -> None:
    o = order(quantity=10, limit=2)
    bad = summary("defective", "segment 2: bead 1.1 mm wide (expected 2.0 mm +-25 %)")
    assert o.count(completed(1, bad)) is Next.CONTINUE
    assert o.count(completed(2, summary("good"))) is Next.CONTINUE  # a good part resets it
    assert o.count(completed(3, bad)) is Next.CONTINUE
    assert o.count(part_of_run("r4", "failed", 4.0, 5.0, None, "flow")) is Next.DEFECT_LIMIT
    reason = o.defect_limit_reason()
    assert "2 defective parts in a row" in reason and "nozzle" in reason
    assert "calibration" in reason and "run failed: flow" in reason


def test_the_report_lists_every_part_in_json_and_csv() -> None:
    o = order(quantity=2)
    o.count(completed(1, summary("good", glue=1.25)))
    o.count(completed(2, None))
    report = report_of(o)
    assert [p["run_id"] for p in report["parts"]] == ["r1", "r2"]
    assert report["glue_ml_total"] == 1.25
    lines = report_csv(o).strip().splitlines()
    assert lines[0].startswith("part,run_id,started_at,ended_at,outcome,verdict")
    assert len(lines) == 3 and ",r2," in lines[2] and NOT_INSPECTED in lines[2]
    assert "not inspected (inspection_enabled is off)" in lines[2]
