"""The dashboard's Settings card in Chromium, against the real server and simulators:
shown to a token that may read the settings, hidden from one that may not; a change
saved from it is in force, named "changed here", and saved in the data directory
(that it is in force again after a restart: tests/integration/test_settings_that_stay.py)."""

from __future__ import annotations

from playwright.async_api import Browser, expect

from tests.browser.test_dashboard import (  # noqa: F401 - the fixture is used by name
    TABLET,
    Dashboard,
    dashboard,
    log_in,
    open_page,
    shot,
)


async def test_the_settings_card_changes_a_setting_that_stays(
    dashboard: Dashboard,  # noqa: F811 - the fixture imported above
    browser: Browser,
) -> None:
    page, problems = await open_page(browser, dashboard, TABLET)
    await log_in(page, dashboard.token)
    card = page.locator(".card-settings")
    await expect(card).to_be_visible()
    shift = page.locator("#setting-shift_hours")
    await expect(shift).to_have_value("8")
    row = card.locator('.setting-row[data-setting="shift_hours"]')
    await expect(row.locator(".setting-source")).to_have_text("default")
    await expect(card.locator('.setting-row[data-setting="robot_ip"]')).to_have_count(0)

    await shift.fill("10")
    await card.locator("#settings-save").scroll_into_view_if_needed()
    await page.click("#settings-save")
    await expect(page.locator("#settings-message")).to_contain_text(
        "Saved: shift_hours 8 → 10. It stays over a restart."
    )
    await expect(row.locator(".setting-source")).to_have_text("changed here")
    assert (await dashboard.rig.api.get("/settings")).json()["shift_hours"] == 10.0
    await shot(page, "settings-card-saved")

    # A value out of bounds: not saved, the server's reason in words, the value kept.
    await shift.fill("-1")
    await page.click("#settings-save")
    message = page.locator("#settings-message")
    await expect(message).to_contain_text("Not saved: invalid request: shift_hours")
    await expect(message).not_to_contain_text("422")
    assert (await dashboard.rig.api.get("/settings")).json()["shift_hours"] == 10.0

    # Kept in the data directory, where a restart finds it.
    saved = (dashboard.rig.cell.settings.data_path / "runtime-settings.json").read_text()
    assert '"shift_hours": 10.0' in saved
    assert not problems, problems


async def test_the_settings_card_is_hidden_from_an_operator(
    dashboard: Dashboard,  # noqa: F811 - the fixture imported above
    browser: Browser,
) -> None:
    created = await dashboard.rig.api.post("/tokens", json={"name": "line 3", "role": "operator"})
    operator = created.json()["token"]
    page, problems = await open_page(browser, dashboard, TABLET)
    await log_in(page, operator)
    await expect(page.locator(".card-kpis")).to_be_visible()
    await page.wait_for_function("() => document.querySelector('.card-settings').hidden")
    await page.click("#logout")
    await log_in(page, dashboard.token)
    await expect(page.locator(".card-settings")).to_be_visible()
    assert not problems, problems
