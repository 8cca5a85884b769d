"""docs/settings.md as generated: every setting once, under its model section."""

from __future__ import annotations

from server.cli.settings_doc import render
from server.settings.model import Settings
from server.settings.reference import facts, groups


def test_every_setting_has_one_row_with_its_variable_default_and_bounds() -> None:
    text = render()
    for setting in facts():
        rows = [line for line in text.splitlines() if line.startswith(f"| `{setting.name}` |")]
        assert len(rows) == 1, setting.name
        assert f"`{setting.variables[0]}`" in rows[0] and setting.accepted in rows[0]
    assert len(facts()) == len(Settings.model_fields)


def test_sections_follow_the_models_comments_in_order() -> None:
    headings = [line[3:] for line in render().splitlines() if line.startswith("## ")]
    assert headings[:3] == ["Core state machine", "Error handling", "Performance monitoring"]
    assert "Safety" in headings and len(headings) == len(set(headings))
    assert groups()["shift_hours"] == "Analytics and the journal"
