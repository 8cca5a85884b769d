"""The dashboard's Trends card in Chromium, against the real server: after a nozzle
clogging over 30 parts, each figure has its small chart, the glue volume's says it is
drifting down, and the defective parts are drawn in red."""

from __future__ import annotations

import random

from playwright.async_api import Browser, expect

from tests.browser.test_dashboard import (  # noqa: F401 - the fixture is used by name
    PANEL,
    Dashboard,
    dashboard,
    log_in,
    open_page,
)
from tests.integration.test_quality_trends import PARTS, clogged_inspection, record_part


async def test_the_trends_card_draws_each_figure_and_names_the_drift(
    dashboard: Dashboard,  # noqa: F811 - the fixture imported above
    browser: Browser,
) -> None:
    noise = random.Random(36)
    for index in range(PARTS):
        run_id = f"clog-{index:02d}"
        await record_part(dashboard.rig, run_id, clogged_inspection(run_id, index, noise))
    page, problems = await open_page(browser, dashboard, PANEL)
    await log_in(page, dashboard.token)
    card = page.locator(".card-trends")
    await expect(card.locator("#trends-count")).to_have_text(f"{PARTS} parts")
    await expect(card.locator(".trend")).to_have_count(5)
    glue = card.locator('.trend[data-figure="glue_volume_percent"]')
    await expect(glue).to_have_attribute("data-drift", "down")
    await expect(glue.locator(".trend-caption.drift")).to_contain_text("drifting down")
    await expect(glue.locator("circle")).to_have_count(PARTS)
    assert await glue.locator("circle.bad").count() > 0  # the defective parts, in red
    await expect(card.locator(".trend-chart").first).to_be_visible()
    assert not problems, problems
