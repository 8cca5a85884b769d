"""The care meter's statuses alone (`item_status`, `pot_status`, `glue_status`) say what the
full judgement (`item_state`, `pot_life`, `glue_level`) says, over arbitrary totals and
settings: the meter checks by the first, GET /maintenance shows the second."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from server.core.worker import care_rules as rules
from server.settings.maintenance import MaintenanceItem, MaintenanceSettings

amounts = st.floats(0.0, 2000.0, allow_nan=False)
items = st.builds(
    MaintenanceItem,
    name=st.just("clean nozzle"),
    every_parts=st.none() | st.integers(1, 50),
    every_ml=st.none() | st.floats(0.5, 500.0),
    every_valve_open_hours=st.none() | st.floats(0.001, 1.0),
)
values = st.fixed_dictionaries(
    {},
    optional={
        "parts": amounts,
        "glue_ml": amounts,
        "valve_open_s": amounts,
        "done:clean nozzle:parts": amounts,
        "done:clean nozzle:glue_ml": amounts,
        rules.LAST_DISPENSE: st.floats(0.0, 10_000.0),
        rules.REFILLED_AT_ML: amounts,
    },
)
care_settings = st.builds(
    MaintenanceSettings,
    maintenance_overdue_percent=st.floats(100.0, 300.0),
    pot_life_minutes=st.none() | st.floats(0.01, 100.0),
    pot_life_warning_percent=st.floats(1.0, 99.0),
    glue_reservoir_ml=st.none() | st.floats(1.0, 1000.0),
    glue_low_level_percent=st.floats(1.0, 99.0),
)


@given(items, values, care_settings, st.floats(0.0, 20_000.0))
def test_the_statuses_alone_agree_with_the_full_judgement(
    item: MaintenanceItem, totals: dict[str, float], settings: MaintenanceSettings, now: float
) -> None:
    plan = rules.item_plan(item)
    assert (
        rules.item_status(plan, totals, settings)
        == (rules.item_state(item, totals, settings)["status"])
    )
    assert rules.item_state(item, totals, settings, plan) == rules.item_state(
        item, totals, settings
    )
    assert (
        rules.pot_status(totals, settings, now) == rules.pot_life(totals, settings, now)["status"]
    )
    assert rules.glue_status(totals, settings) == rules.glue_level(totals, settings)["status"]
