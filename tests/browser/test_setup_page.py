"""The Set-up page in a real browser (Debian's Chromium driven by Playwright) against the
real server on loopback with the simulators (tests/rig.py): reached from the dashboard's
header, it shows the camera's live set-up view and its figures, and stops the stream
when the technician leaves. A screenshot goes to test-artifacts/screenshots/."""

from __future__ import annotations

import asyncio
from pathlib import Path

from playwright.async_api import Browser, Page, expect

from tests.browser.test_dashboard import SHOTS, Problems
from tests.rig import WAIT_S, Rig, open_rig
from tests.serving import admin_headers

PANEL = {"width": 1920, "height": 1080}


async def token(rig: Rig, role: str) -> str:
    created = await rig.api.post("/tokens", json={"name": role, "role": role})
    assert created.status_code == 201, created.text
    return created.json()["token"]


async def sign_in_on_the_dashboard(page: Page, url: str, secret: str) -> None:
    await page.goto(url + "/")
    await page.fill("#token-input", secret)
    await page.click("#login-button")
    await expect(page.locator("#app")).to_be_visible()


async def clients(rig: Rig, data: Path) -> int:
    answer = await rig.api.get("/camera/preview", headers=admin_headers(data))
    return answer.json()["clients"]


async def test_the_set_up_page_shows_the_live_view_and_its_figures(
    tmp_path: Path, browser: Browser
) -> None:
    data = tmp_path / "data"
    async with open_rig(data) as rig:
        url = str(rig.api.base_url).rstrip("/")
        maintenance = await token(rig, "maintenance")
        context = await browser.new_context(viewport=PANEL)
        page = await context.new_page()
        problems = Problems().watch(page)

        # From the dashboard's header to the Set-up page, signed in with the same token.
        await sign_in_on_the_dashboard(page, url, maintenance)
        await page.click("#nav-setup")
        await expect(page).to_have_url(url + "/hmi/setup.html")
        image = page.locator("#setup-image")
        await expect(image).to_be_visible(timeout=WAIT_S * 1000)
        # Frames keep coming, and the figures say what the simulated table holds.
        await page.wait_for_function(  # at least 3: the count may pass 3 between two polls
            "() => Number(document.querySelector('#setup-image').dataset.frames) >= 3",
            timeout=WAIT_S * 1000,
        )
        figures = page.locator("#figures-list")
        await expect(figures).to_have_attribute("data-markers-found", "9")
        await expect(figures).to_contain_text("9 of 9")
        await expect(figures).to_contain_text("Sharpness")
        await expect(figures).to_contain_text("of 255")
        await expect(page.locator("#marker-layout")).to_have_count(1)
        width = await image.evaluate("img => img.naturalWidth")
        assert width > 0
        SHOTS.mkdir(parents=True, exist_ok=True)
        await page.screenshot(path=str(SHOTS / "setup-page.png"))
        assert await clients(rig, data) == 1

        # Back to the dashboard: the stream ends with the page, no capture goes on.
        await page.click("#nav-dashboard")
        await expect(page).to_have_url(url + "/")
        async with asyncio.timeout(WAIT_S):
            while await clients(rig, data) != 0:
                await asyncio.sleep(0.05)
        assert problems == []

        # An operator's token: the dashboard offers no Set-up link; at the page's address
        # the page says why there is no view (the role), and shows none.
        operator = await token(rig, "operator")
        other = await (await browser.new_context(viewport=PANEL)).new_page()
        await sign_in_on_the_dashboard(other, url, operator)
        await expect(other.locator("#nav-setup")).to_be_hidden()
        await other.goto(url + "/hmi/setup.html")
        await expect(other.locator("#setup-status")).to_contain_text("maintenance")
        await expect(other.locator("#setup-image")).to_be_hidden()
        await context.close()
