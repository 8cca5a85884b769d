"""The dashboard's order card in Chromium, against the real server and simulators:
start an order, watch it run to its quantity by itself, hold it with STOP, reset,
resume it from the card, and close it."""

from __future__ import annotations

import asyncio
from typing import Any

from playwright.async_api import Browser, expect

from tests.browser.test_dashboard import (  # noqa: F401 - the fixture is used by name
    PANEL,
    Dashboard,
    dashboard,
    expect_state,
    log_in,
    open_page,
)

RUNS_S = 120_000  # a bound for parts sprayed at the slow demo speed, not a performance figure


async def test_the_order_card_starts_holds_resumes_and_closes(
    dashboard: Dashboard,  # noqa: F811 - the fixture imported above
    browser: Browser,
) -> None:
    # The card, not the parts' verdicts (tests/integration/test_orders.py has those): parts
    # are not inspected here, so they count toward the quantity as "not inspected".
    patched = await dashboard.rig.api.patch("/settings", json={"inspection_enabled": False})
    assert patched.status_code == 200, patched.text
    page, problems = await open_page(browser, dashboard, PANEL)
    await log_in(page, dashboard.token)
    await expect_state(page, "IDLE")
    card = page.locator(".card-order")
    await expect(card.locator("#order")).to_contain_text("No production order yet")
    await expect(page.locator("#order-resume")).to_be_disabled()

    # An order of 2: both parts run from this one click.
    await page.fill("#order-quantity", "2")
    await page.click("#order-start")
    await expect(page.locator("#message")).to_contain_text("started: 2 × demo")
    await expect(page.locator("#order-state")).to_have_text("completed", timeout=RUNS_S)
    await expect(card.locator("#order")).to_contain_text("0 + 2 not inspected / 2")

    # Another, held by STOP mid-part; nothing continues until it is resumed here.
    await page.fill("#order-quantity", "3")
    await page.click("#order-start")
    await expect(page.locator("#order-state")).to_have_text("running")
    await expect_state(page, "EXECUTING_TRAJECTORY")
    await page.click("#estop")
    await expect_state(page, "ERROR")
    await page.click('[data-command="reset"]')
    await expect_state(page, "IDLE")
    await expect(page.locator("#order-state")).to_have_text("held")
    await expect(card.locator(".order-reason")).to_be_visible()
    # The left column says an order waits, and offers its next action.
    await expect(page.locator("#state-order")).to_contain_text("held")
    await expect(page.locator("#state-order")).to_contain_text("Resume order")
    await page.click("#state-order-resume")
    await expect(page.locator("#message")).to_contain_text("resumed")
    await expect(page.locator("#message")).not_to_contain_text("200")
    await expect(page.locator("#order-state")).to_have_text("running")
    await page.click("#order-close")
    await expect(page.locator("#order-state")).to_have_text("closed")
    await expect(page.locator("#order-close")).to_be_disabled()
    assert not problems, problems


async def test_a_double_tap_on_start_order_makes_one_order(
    dashboard: Dashboard,  # noqa: F811 - the fixture imported above
    browser: Browser,
) -> None:
    """Two orders were made, and the second ran after the first: twice the parts. A tap
    while the request is out is ignored; a tap once an order is active asks first."""
    page, problems = await open_page(browser, dashboard, PANEL)
    asked: list[str] = []

    async def decline(dialog: Any) -> None:
        asked.append(dialog.message)
        await dialog.dismiss()

    page.on("dialog", decline)
    await log_in(page, dashboard.token)
    await expect_state(page, "IDLE")
    await page.fill("#order-quantity", "1")
    await page.dblclick("#order-start")  # both taps while the first is on its way
    await expect(page.locator("#message")).to_contain_text("started: 1 × demo")
    await page.wait_for_timeout(200)  # a slower double tap: the first answered by now
    await page.click("#order-start")
    async with asyncio.timeout(10):
        while not asked:
            await asyncio.sleep(0.05)
    orders = (await dashboard.rig.api.get("/orders")).json()["orders"]
    assert len(orders) == 1, orders
    assert asked and "Queue another order" in asked[0], asked
    closed = await dashboard.rig.api.post(f"/orders/{orders[0]['order_id']}/close")
    assert closed.status_code == 200, closed.text
    assert not problems, problems
