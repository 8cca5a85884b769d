"""The Set-up page is safe to work from, in Chromium at the panel sizes, in each state the
cell can be in while a technician works there (IDLE, a run, PAUSED, ERROR after the
page's own STOP), against the real server and simulators.

At every size and state: STOP and the cell's state are on screen, every control is
touch-sized (at least 44 px), and in IDLE the camera's view and the jog buttons are on
one screen; Home, jog and teach are live only where the server would accept them (IDLE,
a maintenance token), and the view the server ends when the cell leaves IDLE opens
again by itself when the cell is back in IDLE. Screenshots go to
test-artifacts/screenshots/setup/. One rig and one browser for the module.
"""

from __future__ import annotations

import asyncio
import re

from playwright.async_api import Browser, Page, expect

from tests.browser.test_dashboard import (  # noqa: F401 - the fixture is used by name
    SHOTS,
    Dashboard,
    Problems,
    dashboard,
)
from tests.rig import WAIT_S

SIZES = (
    {"width": 1024, "height": 768},
    {"width": 1366, "height": 768},
    {"width": 1920, "height": 1080},
)
HTTP_STATUS = re.compile(r"\b(200|201|202|400|403|404|409|422|503)\b")

# Measured in the page: what is off screen, and every visible control under 44 px.
LAYOUT = """(checkCamera) => {
  const problems = [];
  const inView = (el) => { const r = el.getBoundingClientRect();
    return r.width > 0 && r.top >= -0.5 && r.left >= -0.5 && r.bottom <= innerHeight + 0.5
      && r.right <= innerWidth + 0.5; };
  for (const id of ['estop', 'setup-state', 'setup-home']) {
    if (!inView(document.getElementById(id))) problems.push(`#${id} is off screen`);
  }
  if (checkCamera) {
    const image = document.getElementById('setup-image');
    if (image.hidden || !inView(image)) problems.push('the camera view is off screen');
    for (const jog of document.querySelectorAll('[data-jog]')) {
      if (!inView(jog)) problems.push(`jog ${jog.dataset.jog} is off screen`);
    }
  }
  if (document.documentElement.scrollWidth > innerWidth) problems.push('the page scrolls sideways');
  for (const el of document.querySelectorAll('#app button, #app select, #app input, #app a.btn')) {
    const r = el.getBoundingClientRect();
    if (r.width === 0) continue;  // not shown
    const who = el.id || el.textContent;
    if (r.height < 44 || r.width < 44) problems.push(`${who} is ${r.width}×${r.height}`);
  }
  return problems;
}"""


async def setup_page(browser: Browser, cell: Dashboard, token: str) -> tuple[Page, Problems]:
    page = await (await browser.new_context(viewport=SIZES[0])).new_page()
    problems = Problems().watch(page)
    await page.goto(cell.url + "/hmi/setup.html")
    await page.fill("#token-input", token)
    await page.click("#login-form button")
    await expect(page.locator("#app")).to_be_visible()
    return page, problems


async def frames(page: Page) -> int:
    return int(await page.locator("#setup-image").get_attribute("data-frames") or 0)


async def expect_frames_flowing(page: Page) -> None:
    """The view is open and new frames keep arriving."""
    await expect(page.locator("#setup-image")).to_be_visible(timeout=WAIT_S * 1000)
    seen = await frames(page)
    await page.wait_for_function(
        f"() => Number(document.querySelector('#setup-image').dataset.frames) > {seen}",
        timeout=WAIT_S * 1000,
    )


async def expect_controls(page: Page, live: bool) -> None:
    """Home, every jog button and every Teach: all live, or none."""
    controls = [
        page.locator("#setup-home"),
        page.locator("[data-jog]"),
        page.locator("[data-teach]"),
    ]
    for group in controls:
        for index in range(await group.count()):
            item = group.nth(index)
            await (expect(item).to_be_enabled() if live else expect(item).to_be_disabled())


async def check_sizes(page: Page, state: str, *, camera: bool) -> None:
    (SHOTS / "setup").mkdir(parents=True, exist_ok=True)
    for size in SIZES:
        await page.set_viewport_size(size)
        await page.wait_for_timeout(100)  # one layout after the resize
        problems = await page.evaluate(LAYOUT, camera)
        assert problems == [], (state, size, problems)
        name = f"{size['width']}x{size['height']}-{state.lower()}"
        await page.screenshot(path=str(SHOTS / "setup" / f"{name}.png"))


async def test_the_set_up_page_is_safe_in_every_state_at_every_size(
    dashboard: Dashboard,  # noqa: F811 - the fixture imported above
    browser: Browser,
) -> None:
    rig = dashboard.rig
    created = await rig.api.post("/tokens", json={"name": "commissioning", "role": "maintenance"})
    page, problems = await setup_page(browser, dashboard, created.json()["token"])
    state = page.locator("#setup-state")

    # IDLE: everything live, the camera and jog on one screen at every size.
    await expect(state).to_have_text("IDLE")
    await expect_frames_flowing(page)
    await expect_controls(page, live=True)
    await check_sizes(page, "IDLE", camera=True)

    # A run started elsewhere: the view stops, nothing moves the arm from here.
    assert (await rig.api.post("/start")).status_code == 202
    await expect(state).to_have_text("EXECUTING TRAJECTORY")
    await expect_controls(page, live=False)
    await expect(page.locator("#setup-status")).to_contain_text("opens again when the cell is IDLE")
    await check_sizes(page, "EXECUTING", camera=False)
    assert (await rig.api.post("/pause")).status_code == 202
    await expect(state).to_have_text("PAUSED")
    await expect_controls(page, live=False)
    await check_sizes(page, "PAUSED", camera=False)

    # Cancelled: back in IDLE, the view reopens by itself.
    assert (await rig.api.post("/cancel")).status_code == 202
    await expect(state).to_have_text("IDLE")
    await expect_frames_flowing(page)
    await expect_controls(page, live=True)

    # STOP from this page: ERROR, the answer in words, nothing live until a reset.
    await page.click("#estop")
    await expect(state).to_have_text("ERROR")
    await expect_controls(page, live=False)
    message = page.locator("#setup-message")
    await expect(message).to_be_visible()
    assert not HTTP_STATUS.search(await message.text_content() or "")
    await check_sizes(page, "ERROR", camera=False)
    assert (await rig.api.post("/reset")).status_code == 202
    await expect(state).to_have_text("IDLE")
    await expect(message).to_be_hidden()  # it described the stop, which has passed
    await expect_frames_flowing(page)
    await expect_controls(page, live=True)

    # Home from the page: accepted, and the controls wait while the arm moves.
    await page.click("#setup-home")
    await expect(page.locator("#setup-message")).to_contain_text("home")
    async with asyncio.timeout(WAIT_S):
        while (await rig.state())["state"] != "IDLE":
            await asyncio.sleep(0.05)
    assert problems == [], problems


async def test_an_operator_on_the_set_up_page_can_stop_but_not_move_the_arm(
    dashboard: Dashboard,  # noqa: F811 - the fixture imported above
    browser: Browser,
) -> None:
    created = await dashboard.rig.api.post("/tokens", json={"name": "line 3", "role": "operator"})
    page, _ = await setup_page(browser, dashboard, created.json()["token"])
    await expect(page.locator("#setup-state")).to_have_text("IDLE")
    await expect(page.locator("#setup-status")).to_contain_text("maintenance")
    await expect(page.locator("#setup-home")).to_be_disabled()
    await expect(page.locator("[data-jog]")).to_have_count(0)
    await expect(page.locator("#estop")).to_be_enabled()
    await page.click("#estop")
    await expect(page.locator("#setup-state")).to_have_text("ERROR")
    # Why it stopped and whom to call, in words on this page (it has no Reset).
    message = page.locator("#setup-message")
    await expect(message).to_contain_text("Stopped: emergency stop by line 3")
    await expect(message).to_contain_text("Call maintenance to reset: needs the maintenance role")
