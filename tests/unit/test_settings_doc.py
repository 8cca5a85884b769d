"""docs/settings.md as generated: every setting once, under the section that declares it."""

from __future__ import annotations

from server.cli.settings_doc import render
from server.settings.kpis import KpiSettings
from server.settings.model import Settings, sections
from server.settings.reference import facts, groups
from server.settings.section import title_of


def test_every_setting_has_one_row_with_its_variable_default_and_bounds() -> None:
    text = render()
    for setting in facts():
        rows = [line for line in text.splitlines() if line.startswith(f"| `{setting.name}` |")]
        assert len(rows) == 1, setting.name
        assert f"`{setting.variables[0]}`" in rows[0] and setting.accepted in rows[0]
    assert len(facts()) == len(Settings.model_fields)


def test_headings_are_the_sections_in_the_order_of_settings_bases() -> None:
    headings = [line[3:] for line in render().splitlines() if line.startswith("## ")]
    assert headings == [title_of(section) for section in sections()]
    assert len(headings) == len(set(headings))
    assert groups()["shift_hours"] is KpiSettings
    assert "(`KpiSettings`, `server/settings/kpis.py`)" in render()
