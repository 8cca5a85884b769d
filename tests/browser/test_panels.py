"""The dashboard on the HMI panels plants use, in every state the cell can be in.

Each state is reached for real (a run, a pause, a stalled camera holding a
calibration, a device fault and a long stop reason for ERROR, a restart for
INITIALIZING), once; then the viewport goes through every panel size. At each
size every enabled command and STOP must be on screen without scrolling
anything, inside their card, and not covered; no table text may be clipped
without a way to read it. A screenshot of each (size, state) goes to
test-artifacts/screenshots/panels/.
"""

from __future__ import annotations

import asyncio
import dataclasses
import re
from pathlib import Path

from playwright.async_api import Browser, Page, expect

from server.storage.journal.commit_chain import LastCommitFile
from tests.browser.test_dashboard import (
    COMMANDS,
    SHOTS,
    Dashboard,
    Problems,
    dashboard,  # noqa: F401  (the fixture)
    expect_enabled,
    expect_live,
    expect_state,
    log_in,
    open_page,
)
from tests.rig import SPRAY_DEMO, open_rig
from tests.serving import admin_headers, free_port

# The landscape panels plants use.
PANELS = ((1024, 768), (1280, 800), (1366, 768), (1440, 900), (1600, 900), (1920, 1080))
PANEL_SHOTS = SHOTS / "panels"
IDLE_COMMANDS = {"start", "calibrate-robot", "calibrate-camera", "create-workpiece"}
# The longest reason POST /estop takes (EstopRequest.reason: 200 characters).
LONG_REASON = (
    "Operator saw glue strings between the nozzle and the fixture on station 2 while the "
    "robot crossed the clamp; stopped to clean the nozzle and check the clamp before the "
    "next part; see shift log"
)[:200]
CRAWL_MM_S = 3.0  # the demo part's spray speed: a run lasts minutes, time to look at it

# What a panel must show, measured in the page (no scrolling: the page is never scrolled).
LAYOUT_PROBLEMS = """() => {
  const problems = [];
  const name = (el) =>
    el.id ? `#${el.id}` : el.dataset.command ? `[${el.dataset.command}]` : el.className;
  const inside = (r, box) => r.left >= box.left - 0.5 && r.right <= box.right + 0.5
    && r.top >= box.top - 0.5 && r.bottom <= box.bottom + 0.5;
  const viewport = { left: 0, top: 0, right: innerWidth, bottom: innerHeight };
  if (scrollX !== 0 || scrollY !== 0) problems.push(`the page is scrolled to ${scrollY}`);
  if (document.documentElement.scrollWidth > innerWidth) problems.push('the page scrolls sideways');
  const buttons = [...document.querySelectorAll('[data-command]')].filter((b) => !b.disabled);
  for (const button of [...buttons, document.querySelector('#estop')]) {
    const r = button.getBoundingClientRect();
    if (!inside(r, viewport)) problems.push(`${name(button)} is not inside the viewport`);
    const card = button.closest('.card, .topbar');
    if (!inside(r, card.getBoundingClientRect())) {
      problems.push(`${name(button)} is outside its card`);
    }
    // Inside every box that clips it, at its scroll position: visible without scrolling.
    for (let box = button.parentElement; box && box !== document.body; box = box.parentElement) {
      const style = getComputedStyle(box);
      if (style.overflowX === 'visible' && style.overflowY === 'visible') continue;
      if (!inside(r, box.getBoundingClientRect())) {
        problems.push(`${name(button)} is hidden by the scroll area of ${name(box)}`);
      }
    }
    const [x, y] = [(r.left + r.right) / 2, (r.top + r.bottom) / 2];
    const top = document.elementFromPoint(x, y);
    if (!top || !button.contains(top)) {
      problems.push(`${name(button)} is covered by ${top && name(top)}`);
    }
  }
  // The state in full inside its card, and of a stop reason, all or a good part (it scrolls).
  const stateCard = document.querySelector('.card-state').getBoundingClientRect();
  if (!inside(document.querySelector('#state').getBoundingClientRect(), stateCard)) {
    problems.push('the state runs out of its card');
  }
  const fault = document.querySelector('#fault');
  if (!fault.hidden) {
    if (!inside(fault.getBoundingClientRect(), stateCard)) {
      problems.push('the fault runs out of its card');
    }
    if (fault.clientHeight < Math.min(fault.scrollHeight, 100)) {
      problems.push(`only ${fault.clientHeight} px of the stop reason show`);
    }
  }
  // Table text: in full, or with a title; and the whole table within its box: a touch
  // panel shows no scroll bar, so columns past a sideways scroll are as good as clipped.
  for (const wrap of document.querySelectorAll('.table-wrap')) {
    const table = wrap.querySelector('table');
    if (table.scrollWidth > wrap.clientWidth + 1) {
      problems.push(`a table is wider than its box (${table.scrollWidth} > ${wrap.clientWidth})`);
    }
    for (const cell of wrap.querySelectorAll('td, th')) {
      if (cell.scrollWidth > cell.clientWidth + 1 && cell.title !== cell.textContent) {
        problems.push(`table text clipped: "${cell.textContent}"`);
      }
    }
  }
  // The figures beside the tables: no text running out of its tile.
  for (const text of document.querySelectorAll('.kpi-value, .kpi-label, .fact dt, .fact dd')) {
    if (text.scrollWidth > text.clientWidth + 1) {
      problems.push(`text overflows: "${text.textContent}"`);
    }
  }
  return problems;
}"""


async def check_every_panel(page: Page, state: str, enabled: set[str]) -> None:
    """At each panel size: the state shown, the commands offered, nothing out of view."""
    PANEL_SHOTS.mkdir(parents=True, exist_ok=True)
    found: dict[str, list[str]] = {}
    for width, height in PANELS:
        await page.set_viewport_size({"width": width, "height": height})
        await expect_state(page, state)
        await expect_enabled(page, enabled)
        size = f"{width}x{height}"
        await page.screenshot(path=str(PANEL_SHOTS / f"{size}-{state.lower()}.png"))
        problems = await page.evaluate(LAYOUT_PROBLEMS)
        if problems:
            found[size] = problems
    assert not found, f"{state}: {found}"


async def test_commands_and_stop_are_in_view_on_every_panel_in_every_state(
    dashboard: Dashboard,  # noqa: F811
    browser: Browser,
) -> None:
    rig = dashboard.rig
    page, problems = await open_page(browser, dashboard, {"width": 1920, "height": 1080})
    await log_in(page, dashboard.token)
    await check_every_panel(page, "IDLE", IDLE_COMMANDS)

    # A run that lasts: the part sprayed at a crawl. Then held.
    demo = (await rig.api.get("/workpieces/demo")).json()
    crawl = {**demo["spray"], "speed_mm_s": CRAWL_MM_S}
    body = {"name": demo["name"], "outline_mm": demo["outline_mm"], "spray": crawl}
    assert (await rig.api.put("/workpieces/demo", json=body)).status_code == 200
    assert (await rig.api.post("/start", json=SPRAY_DEMO)).status_code == 202
    await expect_state(page, "EXECUTING_TRAJECTORY")
    await expect(page.locator("#progress")).not_to_have_attribute("data-total", "0")
    await check_every_panel(page, "EXECUTING_TRAJECTORY", {"pause", "cancel"})
    assert (await rig.api.post("/pause")).status_code == 202
    await check_every_panel(page, "PAUSED", {"resume", "cancel"})
    assert (await rig.api.post("/cancel")).status_code == 202
    await rig.wait_state("IDLE")

    # Operations held by a stalled camera (each waits for its first frame), then cancelled.
    for command, state in (
        ("calibrate-camera", "CALIBRATING_CAMERA"),
        ("calibrate-robot", "CALIBRATING_ROBOT"),
        ("create-workpiece", "CREATING_WORKPIECE"),
    ):
        rig.camera.inject_fault("stall")
        assert (await rig.api.post(f"/{command}")).status_code == 202
        await check_every_panel(page, state, {"cancel"})
        assert (await rig.api.post("/cancel")).status_code == 202
        await rig.wait_state("IDLE")
        rig.camera.clear_faults()

    # ERROR: stopped with the longest reason, and stopped again (its fault in the message line).
    for reason in (LONG_REASON, LONG_REASON[::-1]):
        response = await rig.api.post("/estop", json={"reason": reason})
        assert response.status_code == 202
        await rig.wait_state("ERROR")
    await expect(page.locator("#fault-message")).to_contain_text(LONG_REASON)
    await check_every_panel(page, "ERROR", {"reset"})
    assert (await rig.reset()).status_code == 202
    await check_every_panel(page, "IDLE", IDLE_COMMANDS)
    assert set(COMMANDS) >= IDLE_COMMANDS
    # The KPI tiles say what they count and in which unit (a stop happened: an MTBF).
    kpi = page.locator("[data-kpi=mtbf] .kpi-value")
    await expect(kpi).to_have_text(re.compile(r"^\d+(\.\d)? (s|min|h|d)$"))
    await expect(page.locator("[data-kpi=workpieces] .kpi-label")).to_have_text(
        "workpieces completed"
    )
    await expect(page.locator("[data-kpi=operations] .kpi-label")).to_have_text(
        "operations completed"
    )
    assert problems == []


async def test_a_restart_forgets_the_old_run_and_initializing_fits_every_panel(
    browser: Browser,
    tmp_path: Path,
) -> None:
    """After the server restarts, the trajectory card shows nothing of the run before it;
    the restarted cell, its camera stalled, stays INITIALIZING while the panels are checked."""
    data, port = tmp_path / "data", free_port()  # the same address after the restart
    context = await browser.new_context(viewport={"width": 1920, "height": 1080})
    page = await context.new_page()
    problems = Problems().watch(page)
    canvas, info = page.locator("#trajectory-canvas"), page.locator("#trajectory-info")
    async with open_rig(data, port=port) as rig:
        await page.goto(str(rig.api.base_url) + "/")
        await log_in(page, admin_headers(data)["Authorization"].split()[1])
        response = await rig.api.post("/start", json={**SPRAY_DEMO, "contour_matching": True})
        assert response.status_code == 202
        await rig.wait_state("IDLE")
        run = (await rig.api.get("/trajectory")).json()["run_id"]
        await expect(info).to_contain_text(f"run {run}")
        await expect(canvas).to_have_attribute("data-background", "camera")
    await expect(page.locator("#banner")).to_be_visible()

    vision_timeout = 120.0  # the stall holds INITIALIZING this long at most
    async with open_rig(
        data, port=port, camera_stalled=True, vision_processing_timeout=vision_timeout
    ) as rig:
        async with asyncio.timeout(vision_timeout):
            await expect_live(page, timeout=30_000)
            await expect_state(page, "INITIALIZING")
            await expect(info).not_to_contain_text(run)
            await expect(info).to_contain_text("no trajectory planned")
            await expect(canvas).not_to_have_attribute("data-background", "camera")
            await expect(page.locator("#progress-run")).not_to_contain_text(run)
            await check_every_panel(page, "INITIALIZING", set())
        rig.camera.clear_faults()
        await expect_state(page, "IDLE")
        await page.reload()
        await expect_live(page)
        await expect(info).to_contain_text("no trajectory planned")
        await expect(canvas).not_to_have_attribute("data-background", "camera")
    # While the server was down on purpose, the browser itself logs each request it could
    # not make (the live link trying again, a card's fetch): that is the restart, not a
    # fault of the page. Anything else the page logged still counts.
    assert [p for p in problems if "net::ERR_CONNECTION_REFUSED" not in p] == []


# The API's "nothing yet" answers on a fresh server: no run planned, no frame captured.
NOTHING_YET = ("/trajectory", "/camera/frame")


async def test_the_page_loads_with_no_console_errors(
    dashboard: Dashboard,  # noqa: F811
    browser: Browser,
) -> None:
    """Every load: no script error and no failed request (the favicon asked no token)."""
    context = await browser.new_context(viewport={"width": 1280, "height": 800})
    page = await context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(f"page error: {error}"))
    page.on(
        "console",
        lambda message: (
            errors.append(f"{message.text} ({message.location.get('url')})")
            if message.type == "error"
            and not (message.location.get("url") or "").endswith(NOTHING_YET)
            else None
        ),
    )
    failed: list[str] = []
    page.on(
        "response",
        lambda response: (
            failed.append(f"{response.status} {response.url}")
            if response.status >= 400 and not response.url.endswith(NOTHING_YET)
            else None
        ),
    )
    await page.goto(dashboard.url + "/")
    await expect(page.locator("#login")).to_be_visible()
    # A shared panel must not keep a token in the browser's password store.
    await expect(page.locator("#token-input")).to_have_attribute("autocomplete", "off")
    await log_in(page, dashboard.token)
    await expect_state(page, "IDLE")
    await page.reload()
    await expect_live(page)
    await expect(page.locator(".workpiece[data-workpiece=demo] img")).to_be_visible()
    await page.wait_for_load_state("networkidle")
    assert (errors, failed) == ([], [])


async def test_a_damaged_journal_shows_on_the_devices_card(
    browser: Browser,
    tmp_path: Path,
) -> None:
    """Damage start-up found in the journal is on /health; the technician sees it too.

    The damage is a lost tail: the commit record outside the database names a commit
    five past the last one the journal holds, as a disk that lost its last writes
    would leave it.
    """
    data = tmp_path / "data"
    async with open_rig(data) as rig:
        assert (await rig.api.post("/home")).status_code == 202
        await rig.wait_state("IDLE")
    journal = data / "journal.db"
    record = LastCommitFile(journal)
    head = record.read()
    assert head is not None
    record.write(dataclasses.replace(head, seq=head.seq + 5))
    record.close()
    async with open_rig(data) as rig:
        assert (await rig.api.get("/health")).json()["journal"]["damage"]
        context = await browser.new_context(viewport={"width": 1280, "height": 800})
        page = await context.new_page()
        await page.goto(str(rig.api.base_url) + "/")
        await log_in(page, admin_headers(data)["Authorization"].split()[1])
        await expect_live(page)
        note = page.locator('.device[data-device="journal"]')
        await expect(note).to_contain_text("damaged")
        await expect(note).to_contain_text("commit")
        await context.close()
