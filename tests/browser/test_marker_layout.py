"""The Set-up page's marker layout panel in a real browser (Debian's Chromium via
Playwright) against the real server with the robot simulator (tests/rig.py):
jog, teach a marker, see the table change."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from playwright.async_api import Browser, expect

from tests.browser.test_dashboard import (
    SHOTS,
    Problems,
)
from tests.rig import open_rig
from tests.serving import admin_headers

TOKEN_KEY = "gluecell.hmi.token"  # clients/hmi/store.js


async def test_jog_then_teach_a_marker_and_see_the_table_change(
    tmp_path: Path,
    browser: Browser,
) -> None:
    data = tmp_path / "data"
    async with open_rig(data, jog_speed_mm_s=200.0) as rig:
        token = admin_headers(data)["Authorization"].split()[1]
        start_x = rig.robot.position[0]
        page = await browser.new_page(viewport={"width": 1280, "height": 800})
        problems = Problems().watch(page)
        await page.add_init_script(
            f"sessionStorage.setItem({json.dumps(TOKEN_KEY)}, {json.dumps(token)})"
        )
        await page.goto(f"{rig.api.base_url}/hmi/setup.html")
        row = page.locator('#marker-table tr[data-marker="4"]')
        await expect(row.locator("td.how")).to_have_text("missing")

        await page.select_option("#jog-step", "10")
        await page.click('button[data-jog="x+"]')
        expected_x = start_x + 10.0
        await expect(page.locator("#marker-robot-position")).to_contain_text(
            f"x {expected_x:.2f}", timeout=30_000
        )
        await expect(page.locator("#marker-robot-position")).not_to_contain_text("moving")
        assert rig.robot.position[0] == pytest.approx(expected_x, abs=0.01)

        await row.locator("button[data-teach]").click()
        await expect(row.locator("td.how")).to_have_text("taught")
        await expect(row.locator('input[name="marker-4-x_mm"]')).to_have_value(f"{expected_x:g}")
        layout = (await rig.api.get("/calibration/markers")).json()
        assert layout["draft"][4]["x_mm"] == pytest.approx(expected_x, abs=0.01)
        assert not await page.locator("#marker-apply").is_enabled()  # eight still missing

        await row.locator('input[name="marker-4-y_mm"]').fill("12.5")
        await row.locator('input[name="marker-4-y_mm"]').press("Enter")
        await expect(row.locator("td.how")).to_have_text("typed")
        layout = (await rig.api.get("/calibration/markers")).json()
        assert layout["draft"][4]["y_mm"] == 12.5
        SHOTS.mkdir(parents=True, exist_ok=True)
        await page.screenshot(path=str(SHOTS / "setup-marker-layout.png"))
        assert problems == []
