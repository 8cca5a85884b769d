"""The run page in a real browser (Debian's Chromium through Playwright) against the real
server with the simulators: after a spray run, the dashboard's Last part card links to the
run's flight recording, which draws the path over the run's frame, charts flow, pressure
and speed, says the inspection's verdict and why the run stopped, and replays it. A
screenshot goes to test-artifacts/screenshots/run-page.png."""

from __future__ import annotations

from pathlib import Path

from playwright.async_api import Browser, expect

from tests.browser.test_dashboard import SHOTS, Problems
from tests.browser.test_setup_page import sign_in_on_the_dashboard, token
from tests.rig import SPRAY_DEMO, WAIT_S, open_rig

PANEL = {"width": 1280, "height": 800}


async def test_the_last_part_opens_its_run_replayed_with_its_charts(
    tmp_path: Path, browser: Browser
) -> None:
    async with open_rig(tmp_path / "data") as rig:
        started = await rig.api.post("/start", json=SPRAY_DEMO)
        assert started.status_code == 202
        run_id = started.json()["run_id"]
        await rig.wait_state("IDLE")
        url = str(rig.api.base_url).rstrip("/")
        viewer = await token(rig, "viewer")
        context = await browser.new_context(viewport=PANEL)
        page = await context.new_page()
        problems = Problems().watch(page)
        await sign_in_on_the_dashboard(page, url, viewer)

        replay = page.locator("#part-replay")
        await expect(replay).to_be_visible(timeout=WAIT_S * 1000)
        await expect(replay).to_have_attribute("href", f"/hmi/run.html?run={run_id}")
        await replay.click()
        await expect(page.locator("body")).to_have_attribute(
            "data-ready", "true", timeout=WAIT_S * 1000
        )
        recording = (await rig.api.get(f"/runs/{run_id}/recording")).json()
        verdict = recording["inspection"]["verdict"]
        await expect(page.locator("#run-verdict")).to_have_text(verdict)
        await expect(page.locator("#run-stop")).to_have_text("no fault stopped it")
        await expect(page.locator("#run-frame")).to_have_text("inspection image")
        for series in ("flow_ml_min", "pressure_psi", "speed_mm_s"):
            chart = page.locator(f'svg[data-series="{series}"]')
            await expect(chart).to_be_visible()
            assert await chart.locator("polyline").count() >= 1, series
        # The valve's open spans are shaded on the charts.
        assert await page.locator('svg[data-series="flow_ml_min"] rect').count() >= 1
        # The replay: at the start the cursor is at 0 and the sample shown is the first one.
        await page.locator("#run-time").fill("0")
        await expect(page.locator("#run-sample")).to_contain_text("valve")
        cursor = page.locator('svg[data-series="flow_ml_min"] .run-cursor')
        await expect(cursor).to_have_attribute("x1", "0")
        SHOTS.mkdir(parents=True, exist_ok=True)
        await page.locator("#run-time").fill("600")
        await page.screenshot(path=str(SHOTS / "run-page.png"))
        assert problems == []
        await context.close()
