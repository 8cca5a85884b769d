"""The dashboard's Maintenance card in Chromium, against the real server and simulators:
the schedule as the server judges it, and an item a purge makes due marked to do."""

from __future__ import annotations

import asyncio

from playwright.async_api import Browser, expect

from tests.browser.test_dashboard import (  # noqa: F401 - the fixture is used by name
    PANEL,
    Dashboard,
    dashboard,
    expect_state,
    log_in,
    open_page,
)


async def test_the_maintenance_card_shows_an_item_a_purge_made_due(
    dashboard: Dashboard,  # noqa: F811 - the fixture imported above
    browser: Browser,
) -> None:
    api = dashboard.rig.api
    items = [
        {"name": "clean nozzle", "every_parts": 200, "every_ml": 500},
        {"name": "empty purge cup", "every_purges": 1},
    ]
    patched = await api.patch("/settings", json={"maintenance_items": items, "purge_seconds": 0.2})
    assert patched.status_code == 200, patched.text
    page, problems = await open_page(browser, dashboard, PANEL)
    await log_in(page, dashboard.token)
    await expect_state(page, "IDLE")
    card = page.locator(".card-maintenance")
    await expect(card).to_contain_text("clean nozzle")
    await expect(page.locator("#maintenance-status")).to_have_text("ok")

    assert (await api.post("/purge")).status_code == 202
    async with asyncio.timeout(60):
        while (await api.get("/maintenance")).json()["counters"]["purges"] < 1:
            await asyncio.sleep(0.05)
    await expect(page.locator("#maintenance-status")).to_have_text("1 to do")
    await expect(card.locator(".fact.warn")).to_contain_text("empty purge cup")
    await expect(card.locator(".fact.warn")).to_contain_text("due")
    assert problems == [], problems
