"""The one verdict of a part (server/quality/part_verdict.py), on run records as data:
every path (the order, GET /operations, the KPIs, the CSV, MQTT, OPC UA, webhooks)
takes its words from here."""

from __future__ import annotations

import pytest

from server.quality.part_verdict import PartVerdict, part_verdict, verdict_details

GAP = "segment 3: a gap of 14.2 mm without bead (at most 3.0 mm)"


def inspected(verdict: str, *reasons: str) -> dict:
    return {"inspection": {"verdict": verdict, "reasons": list(reasons), "glue_ml": 1.5}}


@pytest.mark.parametrize(
    ("outcome", "result", "error", "expected"),
    [
        ("completed", inspected("good"), None, PartVerdict("good", True, ())),
        ("completed", inspected("defective", GAP), None, PartVerdict("defective", True, (GAP,))),
        (
            "failed",
            None,
            "EMERGENCY_STOP",
            PartVerdict("defective", False, ("run stopped: emergency stop (STOP)",)),
        ),
        (
            "failed",
            None,
            "robot: link lost",
            PartVerdict("defective", False, ("run failed: robot: link lost",)),
        ),
        ("cancelled", None, None, PartVerdict("defective", False, ("run cancelled",))),
        (
            "interrupted",
            None,
            "the server stopped during the operation",
            PartVerdict("defective", False, ("run cut short: the server stopped during it",)),
        ),
        (
            "completed",
            {"waypoints": 9},
            None,
            PartVerdict("not_inspected", False, ("not inspected (inspection_enabled is off)",)),
        ),
        (
            "completed",
            {"not_inspected": "no space", "inspection_found": {"verdict": "good", "reasons": []}},
            None,
            PartVerdict("not_inspected", False, ("not inspected (no space)",)),
        ),
        (
            "completed",
            {
                "not_inspected": "no space",
                "inspection_found": {"verdict": "defective", "reasons": [GAP]},
            },
            None,
            PartVerdict("defective", False, ("not inspected (no space)", GAP)),
        ),
        # A verdict outside the contract is not guessed at.
        (
            "completed",
            {"inspection": {"verdict": "maybe"}},
            None,
            PartVerdict("not_inspected", False, ("not inspected (inspection_enabled is off)",)),
        ),
    ],
)
def test_each_way_a_run_ends_gives_one_verdict(
    outcome: str, result: dict | None, error: str | None, expected: PartVerdict
) -> None:
    assert part_verdict(outcome, result, error) == expected


def test_the_labels_are_the_words_a_person_reads() -> None:
    assert part_verdict("completed", inspected("good")).label == "good"
    assert part_verdict("completed", inspected("defective", GAP)).label == "defective"
    assert part_verdict("cancelled", None).label == "defective (not inspected)"
    off = part_verdict("completed", {}).label
    assert off == "not inspected (inspection_enabled is off)"


def test_a_run_that_makes_no_part_has_no_verdict_in_a_message() -> None:
    details = verdict_details("calibrate_robot", "completed", {"residual_mm": 0.2}, None)
    assert (details["verdict"], details["inspected"], details["reasons"]) == (None, False, [])
    stopped = verdict_details("trajectory", "failed", None, "EMERGENCY_STOP")
    assert (stopped["verdict"], stopped["label"], stopped["inspection"]) == (
        "defective",
        "defective (not inspected)",
        None,
    )
