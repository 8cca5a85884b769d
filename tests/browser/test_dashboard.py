"""The operator dashboard in a real browser: Debian's Chromium driven by Playwright,
against the real server on loopback with the robot and glue simulators (tests/rig.py).

Screenshots of each step go to test-artifacts/screenshots/. With UPDATE_SCREENSHOT=1
the run also rewrites docs/dashboard.png (1920×1080, taken mid-run).
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi import FastAPI
from playwright.async_api import Browser, ConsoleMessage, Page, expect

from server.api import openapi_doc
from server.api.dashboard import mount_dashboard
from server.bootstrap.app import create_app
from server.security.policy import POLICY
from tests import serving
from tests.rig import Rig, append_inspected_run, open_rig
from tests.serving import admin_headers

ROOT = Path(__file__).resolve().parents[2]
SHOTS = ROOT / "test-artifacts" / "screenshots"
DOC_SHOT = ROOT / "docs" / "dashboard.png"
PANEL = {"width": 1920, "height": 1080}
TABLET = {"width": 1024, "height": 768}
# Chromium logs every 4xx answer to the console; the tests expect some (401, 409).
HTTP_STATUS_LOG = "Failed to load resource: the server responded with a status of"
SLOW_SPRAY_MM_S = 30.0  # the demo part sprays in a few seconds: time to watch and to stop it
COMMANDS = (
    "start",
    "pause",
    "resume",
    "cancel",
    "calibrate-robot",
    "calibrate-camera",
    "create-workpiece",
    "reset",
)


@dataclass
class Dashboard:
    rig: Rig
    app: FastAPI
    url: str
    token: str
    baseline_subscriptions: set[int]

    def drop_websockets_server_side(self) -> int:
        """Close every WebSocket client's bus subscription: the server closes them (4001)."""
        bus = self.rig.cell.worker.bus
        clients = [s for s in bus._subscribers if id(s) not in self.baseline_subscriptions]
        for subscription in clients:
            subscription.close("dropped by the test")
        return len(clients)


@pytest.fixture
async def dashboard(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> AsyncIterator[Dashboard]:
    """The rig's server with the dashboard mounted (a no-op if the app already mounts it)."""
    apps: list[FastAPI] = []

    def create_app_with_dashboard(*args: Any, **kwargs: Any) -> FastAPI:
        app = create_app(*args, **kwargs)
        mount_dashboard(app)
        apps.append(app)
        return app

    monkeypatch.setattr(serving, "create_app", create_app_with_dashboard)
    if ("GET", "/") not in POLICY:  # until the policy opens the page: server/api/dashboard.py
        declared = openapi_doc.required_role
        monkeypatch.setattr(
            openapi_doc,
            "required_role",
            lambda method, path: None if (method, path) == ("GET", "/") else declared(method, path),
        )
    data = tmp_path / "data"
    async with open_rig(data) as rig:
        demo = (await rig.api.get("/workpieces/demo")).json()
        slow = {**demo["spray"], "speed_mm_s": SLOW_SPRAY_MM_S}
        body = {"name": demo["name"], "outline_mm": demo["outline_mm"], "spray": slow}
        assert (await rig.api.put("/workpieces/demo", json=body)).status_code == 200
        token = admin_headers(data)["Authorization"].split()[1]
        baseline = {id(s) for s in rig.cell.worker.bus._subscribers}
        yield Dashboard(rig, apps[0], str(rig.api.base_url), token, baseline)


class Problems(list[str]):
    """A page's script errors and console errors (besides the 4xx answers a test expects)."""

    def watch(self, page: Page) -> Problems:
        page.on("pageerror", lambda error: self.append(f"page error: {error}"))
        page.on("console", self.on_console)
        return self

    def on_console(self, message: ConsoleMessage) -> None:
        if message.type == "error" and not message.text.startswith(HTTP_STATUS_LOG):
            self.append(f"console error: {message.text}")


async def open_page(
    browser: Browser, dashboard: Dashboard, viewport: dict[str, int]
) -> tuple[Page, Problems]:
    context = await browser.new_context(viewport=viewport)
    page = await context.new_page()
    problems = Problems().watch(page)
    await page.goto(dashboard.url + "/")
    return page, problems


async def log_in(page: Page, token: str) -> None:
    await page.fill("#token-input", token)
    await page.click("#login-button")
    await expect(page.locator("#app")).to_be_visible()
    await expect_live(page)


async def expect_live(page: Page, timeout: float = 10_000) -> None:
    await expect(page.locator("#link")).to_have_attribute("data-live", "true", timeout=timeout)
    await expect(page.locator("#state")).to_have_attribute("data-stale", "false")
    await expect(page.locator("#banner")).to_be_hidden()


async def expect_state(page: Page, state: str, timeout: float = 15_000) -> None:
    await expect(page.locator("#state")).to_have_attribute("data-state", state, timeout=timeout)


async def expect_enabled(page: Page, enabled: set[str]) -> None:
    """Exactly `enabled` command buttons are enabled; STOP always is."""
    for name in COMMANDS:
        button = page.locator(f'[data-command="{name}"]')
        if name in enabled:
            await expect(button, f"{name} should be enabled").to_be_enabled()
        else:
            await expect(button, f"{name} should be disabled").to_be_disabled()
    await expect(page.locator("#estop")).to_be_visible()
    await expect(page.locator("#estop")).to_be_enabled()


async def shot(page: Page, name: str, *, full_page: bool = False) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    await page.screenshot(path=str(SHOTS / f"{name}.png"), full_page=full_page)


async def progress(page: Page) -> tuple[int, int]:
    bar = page.locator("#progress")
    return int(await bar.get_attribute("data-waypoint") or 0), int(
        await bar.get_attribute("data-total") or 0
    )


async def watch_progress(
    page: Page, seen: set[tuple[int, int]], done: Callable[[int, str], bool]
) -> None:
    """Record each (waypoint, of) the bar shows until `done(waypoint, state)`."""
    async with asyncio.timeout(30):
        while True:
            waypoint, of = await progress(page)
            if waypoint:
                seen.add((waypoint, of))
            if done(waypoint, await page.locator("#state").get_attribute("data-state") or ""):
                return
            await asyncio.sleep(0.05)


async def executed_pixels(page: Page) -> int:
    """Pixels of the trajectory canvas in the colour of the executed path (#ff4fd8)."""
    return await page.evaluate(
        """() => {
            const canvas = document.querySelector('#trajectory-canvas');
            const { width, height } = canvas;
            const data = canvas.getContext('2d').getImageData(0, 0, width, height).data;
            let count = 0;
            for (let i = 0; i < data.length; i += 4) {
                const [r, g, b] = [data[i], data[i + 1], data[i + 2]];
                if (r > 230 && Math.abs(g - 79) < 30 && Math.abs(b - 216) < 30) count += 1;
            }
            return count;
        }"""
    )


async def test_the_page_and_its_assets_are_served_without_a_token(dashboard: Dashboard) -> None:
    async with httpx.AsyncClient(base_url=dashboard.url) as anonymous:
        page = await anonymous.get("/")
        assert page.status_code == 200
        assert page.headers["content-type"].startswith("text/html")
        assert "frame-ancestors 'none'" in page.headers["content-security-policy"]
        assert '<script src="/hmi/app.js"' in page.text
        for asset, kind in (("/hmi/app.js", "javascript"), ("/hmi/style.css", "text/css")):
            response = await anonymous.get(asset)
            assert response.status_code == 200 and kind in response.headers["content-type"]
        assert (await anonymous.get("/hmi/missing.js")).status_code == 404
        assert (await anonymous.get("/state")).status_code == 401  # the API stays closed


async def test_login_refuses_a_wrong_token_and_fits_a_tablet(
    dashboard: Dashboard, browser: Browser
) -> None:
    page, problems = await open_page(browser, dashboard, TABLET)
    await expect(page.locator("#login")).to_be_visible()
    await page.fill("#token-input", "gc_wrong_token")
    await page.click("#login-button")
    await expect(page.locator("#login-error")).to_have_text("the token is unknown or revoked")
    await shot(page, "01-login-refused")

    await log_in(page, dashboard.token)
    await expect_state(page, "IDLE")
    assert await page.evaluate("sessionStorage.length") == 1
    ticking = await page.locator("#state-time").inner_text()
    await expect(page.locator("#state-time")).not_to_have_text(ticking, timeout=3000)
    # A tablet: no sideways scrolling, STOP on screen, touch-sized buttons.
    assert await page.evaluate("document.documentElement.scrollWidth <= window.innerWidth")
    await expect(page.locator("#estop")).to_be_in_viewport()
    box = await page.locator('[data-command="start"]').bounding_box()
    assert box is not None and box["height"] >= 56
    await expect(page.locator(".workpiece[data-workpiece=demo] img")).to_be_visible()
    await shot(page, "02-tablet", full_page=True)
    # The token survives a reload of the tab, and the page goes live again.
    await page.reload()
    await expect_live(page)
    assert problems == []


async def test_a_cycle_then_stop_mid_run_then_reset(dashboard: Dashboard, browser: Browser) -> None:
    page, problems = await open_page(browser, dashboard, PANEL)
    await log_in(page, dashboard.token)
    await expect_state(page, "IDLE")
    await expect_enabled(page, {"start", "calibrate-robot", "calibrate-camera", "create-workpiece"})
    await expect(page.locator(".workpiece[data-workpiece=demo] img")).to_be_visible()
    await expect(page.locator("[data-device=glue]")).to_have_attribute("data-connected", "true")
    assert await executed_pixels(page) == 0
    # No camera frame since the server started: the path goes over the calibration image.
    canvas = page.locator("#trajectory-canvas")
    await expect(canvas).to_have_attribute("data-background", "calibration")

    # A whole run, paused and resumed on the way: the bar moves, then IDLE.
    await page.click('[data-command="start"]')
    await expect(page.locator("#message")).to_contain_text("start accepted")
    await expect_state(page, "EXECUTING_TRAJECTORY")
    await expect_enabled(page, {"pause", "cancel"})
    # The run looked at the table: its frame is now under the path (GET /camera/frame).
    await expect(canvas).to_have_attribute("data-background", "camera")
    await expect(page.locator("#trajectory-info")).to_contain_text("camera")
    await expect(page.locator("#trajectory-info")).to_contain_text("(trajectory)")
    seen: set[tuple[int, int]] = set()
    await watch_progress(page, seen, lambda waypoint, _: waypoint >= 3)
    await page.click('[data-command="pause"]')
    await expect_state(page, "PAUSED")
    await expect(page.locator("#state")).to_have_attribute("data-tone", "hold")
    await expect_enabled(page, {"resume", "cancel"})
    await shot(page, "03-paused")
    await page.click('[data-command="resume"]')
    await expect_state(page, "EXECUTING_TRAJECTORY")
    await watch_progress(page, seen, lambda _, state: state == "IDLE")
    assert len(seen) >= 2, f"the progress bar did not move: {seen}"
    of = max(total for _, total in seen)
    await expect(page.locator("#progress")).to_have_attribute("data-waypoint", str(of))
    await expect(page.locator("#progress")).to_have_attribute("aria-valuenow", "100")
    await expect(page.locator("#progress-note")).to_have_text("last run completed")
    await expect(page.locator("#progress-workpiece")).to_have_text("demo")
    # Paused and resumed, the part got the glue of its path once: the Last part card says good.
    await expect(page.locator("#part-verdict")).to_have_text("good")
    await expect(page.locator("#part-reasons li")).to_have_count(0)
    await expect_enabled(page, {"start", "calibrate-robot", "calibrate-camera", "create-workpiece"})
    await shot(page, "04-run-completed")

    # Again, and STOP mid-run: ERROR with the first-out reason and what to do.
    await page.click('[data-command="start"]')
    await expect_state(page, "EXECUTING_TRAJECTORY")
    await page.wait_for_function(
        "n => Number(document.querySelector('#progress').dataset.waypoint) >= n",
        arg=of // 2,
        timeout=15_000,
    )
    await expect(page.locator("#trajectory-info")).to_contain_text(f"{of} waypoints")
    assert await executed_pixels(page) > 100, "the executed part of the path is not drawn"
    await shot(page, "05-running")
    if os.environ.get("UPDATE_SCREENSHOT") == "1":
        await page.screenshot(path=str(DOC_SHOT))
    await page.click("#estop")
    await expect_state(page, "ERROR")
    await expect(page.locator("#fault")).to_be_visible()
    await expect(page.locator("#fault-message")).to_contain_text("emergency stop")
    await expect(page.locator("#fault-message")).to_contain_text("STOP pressed on the HMI")
    await expect(page.locator("#fault-action")).not_to_be_empty()
    await expect(page.locator("#progress-note")).to_have_text("last run stopped")
    await expect_enabled(page, {"reset"})
    assert not dashboard.rig.glue.valve_open
    await shot(page, "06-stopped")

    await page.click('[data-command="reset"]')
    await expect(page.locator("#message")).to_contain_text("reset accepted")
    await expect_state(page, "IDLE")
    await expect(page.locator("#fault")).to_be_hidden()
    await expect_enabled(page, {"start", "calibrate-robot", "calibrate-camera", "create-workpiece"})
    # History and KPIs follow (refreshed on each change and every few seconds).
    history = page.locator("#history tr")
    await expect(history.first).to_contain_text("RESET_REQUESTED")
    await expect(page.locator("#history")).to_contain_text("EMERGENCY_STOP")
    await expect(page.locator('[data-kpi="workpieces"] .kpi-value')).to_have_text("1")
    await shot(page, "07-reset")
    assert problems == []


async def test_the_state_card_names_the_live_run_and_a_reset_clears_the_fault_message(
    dashboard: Dashboard, browser: Browser
) -> None:
    """Two things a page left as they were: the run's line stayed empty for a run started
    while the page watched (the state's snapshot is taken before the run starts), and the
    red fault message stayed after a reset another client made."""
    page, problems = await open_page(browser, dashboard, PANEL)
    await log_in(page, dashboard.token)
    await expect_state(page, "IDLE")
    api = dashboard.rig.api
    started = await api.post("/start", json={"contour_matching": False, "workpiece_id": "demo"})
    assert started.status_code == 202, started.text
    await expect_state(page, "EXECUTING_TRAJECTORY")
    run_id = started.json()["run_id"]
    await expect(page.locator("#state-operation")).to_have_text(
        f"operation trajectory · run {run_id}"
    )
    assert (await api.post("/estop", json={"reason": "guard door 2 opened"})).status_code == 202
    await expect_state(page, "ERROR")
    message = page.locator("#message")
    await expect(message).to_contain_text("fault EMERGENCY_STOP")
    assert (await api.post("/reset")).status_code == 202
    await expect_state(page, "IDLE")
    await expect(message).to_be_hidden()
    await expect(page.locator("#state-operation")).to_have_text("")
    assert problems == []


async def test_a_stop_that_could_not_be_sent_is_not_forgotten_when_the_page_is_live_again(
    dashboard: Dashboard, browser: Browser
) -> None:
    """The "could not reach the server" message went with the reconnection, though that
    stop was never made; now the page says so, with the state the cell is in."""
    page, problems = await open_page(browser, dashboard, PANEL)
    page.on("dialog", lambda dialog: asyncio.ensure_future(dialog.accept()))
    await log_in(page, dashboard.token)
    await expect_state(page, "IDLE")
    hub = dashboard.app.state.ws_hub
    limit, hub.max_clients = hub.max_clients, 0
    assert dashboard.drop_websockets_server_side() == 1
    await expect(page.locator("#banner")).to_be_visible()
    await page.route("**/estop", lambda route: route.abort())  # the server out of reach
    await page.click("#estop")
    message = page.locator("#message")
    await expect(message).to_contain_text("STOP could not reach the server")
    await page.unroute("**/estop")
    hub.max_clients = limit
    await expect_live(page, timeout=15_000)
    await expect(message).to_contain_text("a STOP pressed while the server was unreachable")
    await expect(message).to_contain_text("the cell is IDLE")
    assert (await dashboard.rig.api.post("/estop")).status_code == 202
    await expect_state(page, "ERROR")
    await expect(message).not_to_contain_text("was not made")
    problems[:] = [p for p in problems if "ERR_FAILED" not in p and "estop" not in p]
    assert problems == []


async def test_the_devices_card_is_live_and_does_not_poll(
    dashboard: Dashboard, browser: Browser
) -> None:
    """Valve, flow and the robot's pose arrive as /ws `device` messages: the card shows the
    valve open while glue flows and closed right after STOP, with no 3 s poll of /health."""
    page, problems = await open_page(browser, dashboard, PANEL)
    await log_in(page, dashboard.token)
    await expect_state(page, "IDLE")
    glue, robot = page.locator("[data-device=glue]"), page.locator("[data-device=robot]")
    await expect(glue).to_have_attribute("data-valve", "closed")
    polls: list[str] = []
    page.on("request", lambda r: polls.append(r.url) if r.url.endswith("/health") else None)
    await asyncio.sleep(7.0)  # more than twice the old 3 s refresh, live and idle
    assert polls == [], "the devices card polled /health while the page was live"

    await page.click('[data-command="start"]')
    await expect_state(page, "EXECUTING_TRAJECTORY")
    await expect(glue).to_have_attribute("data-valve", "open", timeout=15_000)
    await expect(glue.locator(".fact", has_text="valve")).to_contain_text("OPEN")
    position = robot.locator(".fact", has_text="position")
    first = await position.inner_text()
    await expect(position).not_to_have_text(first)  # the pose follows the arm
    await shot(page, "08-devices-live")
    await page.click("#estop")
    await expect_state(page, "ERROR")
    await expect(glue).to_have_attribute("data-valve", "closed")
    assert not dashboard.rig.glue.valve_open
    await page.click('[data-command="reset"]')
    await expect_state(page, "IDLE")
    assert problems == []


GAP_REASON = "segment 3: a gap of 14.2 mm without bead (at most 3.0 mm)"


# A defective part's record, as the inspection's contract writes it into a run's result.
DEFECTIVE_PART = {
    "verdict": "defective",
    "reasons": [GAP_REASON],
    "precision_mean_mm": 0.31,
    "precision_p95_mm": 0.74,
    "dispensing_cv_percent": 4.2,
    "glue_ml": 1.35,
    "vision_residual_mm": 0.18,
    "image": True,
}


async def test_the_last_part_card_shows_the_verdict_live_and_on_load(
    dashboard: Dashboard, browser: Browser
) -> None:
    page, problems = await open_page(browser, dashboard, PANEL)
    await log_in(page, dashboard.token)
    await expect_state(page, "IDLE")
    part, verdict = page.locator("#part"), page.locator("#part-verdict")
    await expect(verdict).to_have_text("no part yet")
    await expect(part).to_have_attribute("data-verdict", "none")

    # A real run ends: the card follows at once (no reload) with its inspection's verdict,
    # reasons and annotated image.
    await page.click('[data-command="start"]')
    await expect_state(page, "EXECUTING_TRAJECTORY")
    await expect_state(page, "IDLE")
    api = dashboard.rig.api
    [real] = (await api.get("/operations", params={"limit": 1})).json()["operations"]
    inspection = (await api.get(f"/runs/{real['run_id']}/inspection")).json()
    await expect(part).to_have_attribute("data-run", real["run_id"])
    # The whole run id: its first 8 characters are the server process's, every run's alike.
    await expect(page.locator("#part-run")).to_contain_text(f"run {real['run_id']}")
    await expect(verdict).to_have_text(inspection["verdict"])
    await expect(part).to_have_attribute("data-verdict", inspection["verdict"])
    await expect(page.locator("#part-reasons li")).to_have_count(len(inspection["reasons"]))
    await expect(page.locator("#part-image")).to_be_visible()
    await expect(page.locator("#part-image")).to_have_js_property("complete", True)
    assert await page.locator("#part-image").evaluate("img => img.naturalWidth") > 0

    # An inspected, defective part's record: shown when the page loads, with its reasons
    # and figures. Its image is asked for; a server that has none (404) leaves no picture.
    await append_inspected_run(dashboard.rig, "run-defective-1", DEFECTIVE_PART)
    images: list[str] = []
    page.on("request", lambda r: images.append(r.url) if "/inspection.jpg" in r.url else None)
    await page.reload()
    await expect_live(page)  # the tab kept its token: the session starts again by itself
    await expect(part).to_have_attribute("data-run", "run-defective-1")
    await expect(verdict).to_have_text("defective")
    await expect(verdict).to_have_attribute("data-kind", "fault")
    await expect(page.locator("#part-reasons li")).to_have_text([GAP_REASON])
    await expect(page.locator("#part-figures")).to_contain_text("0.74 mm")
    await expect(page.locator("#part-figures")).to_contain_text("1.35 ml")
    await expect(page.locator("#part-image")).to_be_hidden()
    await expect(page.locator("#part-image-note")).to_have_text("no inspection image kept")
    assert any(url.endswith("/runs/run-defective-1/inspection.jpg") for url in images)
    # The real part and the defective record: the KPI tiles count both.
    good = int(inspection["verdict"] == "good")
    await expect(page.locator('[data-kpi="defective"] .kpi-value')).to_have_text(str(2 - good))
    await expect(page.locator('[data-kpi="quality"] .kpi-value')).to_have_text(
        f"{50.0 * good:.1f} %"
    )
    await shot(page, "09-last-part-defective")
    assert problems == []


async def test_refusals_show_the_servers_message(dashboard: Dashboard, browser: Browser) -> None:
    """403 for a role too low, 409 for a command the state forbids: the server's words, with
    no HTTP status. The page does not offer the viewer Start; a press forced on the hidden
    button still gets the server's refusal, and nothing changes."""
    created = await dashboard.rig.api.post("/tokens", json={"name": "hall", "role": "viewer"})
    viewer = created.json()["token"]
    page, problems = await open_page(browser, dashboard, PANEL)
    await log_in(page, viewer)
    start = page.locator('[data-command="start"]')
    await expect(start).to_be_hidden()  # the state allows it, the role does not: not offered
    await start.evaluate("button => { button.hidden = false; button.disabled = false; }")
    await start.click()
    await expect(page.locator("#message")).to_contain_text(
        "this needs the operator role; hall has viewer"
    )
    await expect(page.locator("#message")).not_to_contain_text("403")
    await expect_state(page, "IDLE")

    await page.click("#logout")
    await expect(page.locator("#login")).to_be_visible()
    await log_in(page, dashboard.token)
    resume = page.locator('[data-command="resume"]')
    await expect(resume).to_be_disabled()
    await resume.evaluate("button => { button.disabled = false; button.click(); }")
    await expect(page.locator("#message")).to_contain_text("resume is not allowed in IDLE")
    await expect(resume).to_be_disabled()
    assert problems == []


async def test_connection_loss_shows_the_banner_marks_state_stale_and_reconnects(
    dashboard: Dashboard, browser: Browser
) -> None:
    page, problems = await open_page(browser, dashboard, PANEL)
    await log_in(page, dashboard.token)
    await expect_state(page, "IDLE")
    hub = dashboard.app.state.ws_hub
    limit = hub.max_clients
    connects = (await page.evaluate("window.hmi.status()"))["connects"]

    # The server drops the socket and refuses new ones for a while.
    hub.max_clients = 0
    assert dashboard.drop_websockets_server_side() == 1
    banner = page.locator("#banner")
    await expect(banner).to_be_visible()
    await expect(banner).to_contain_text("Connection lost — reconnecting")
    await expect(page.locator("#state")).to_have_attribute("data-stale", "true")
    await expect(page.locator("#stale-badge")).to_be_visible()
    await expect(page.locator("#link-text")).to_have_text("connection lost")
    await expect_enabled(page, set())  # nothing is offered on a state that is not live
    # Meanwhile the cell stops: the page must not show the old state as live.
    assert (await dashboard.rig.api.post("/estop")).status_code == 202
    async with asyncio.timeout(10):
        while (await page.evaluate("window.hmi.status()"))["attempts"] < 2:
            await asyncio.sleep(0.05)
    await expect(banner).to_contain_text("too many clients")
    await expect_state(page, "IDLE")
    await expect(page.locator("#state")).to_have_attribute("data-stale", "true")
    await shot(page, "08-connection-lost")

    # The server takes clients again: the page reconnects by itself, with the new state.
    hub.max_clients = limit
    await expect_live(page, timeout=15_000)
    await expect_state(page, "ERROR")
    await expect_enabled(page, {"reset"})
    status = await page.evaluate("window.hmi.status()")
    assert status["connects"] == connects + 1 and status["attempts"] == 0
    await shot(page, "09-reconnected")

    # The page's own hook: the socket closes, the banner shows, the page reconnects.
    await page.evaluate("window.hmi.dropConnection()")
    await expect(banner).to_be_visible()
    await expect_live(page, timeout=10_000)
    assert (await page.evaluate("window.hmi.status()"))["connects"] == connects + 2
    assert problems == []


async def test_a_stored_workpiece_is_still_said_when_its_answer_comes_after_its_end(
    dashboard: Dashboard, browser: Browser
) -> None:
    """The capture can end (over the socket) before its POST's 202 reaches the page: the
    late "accepted" must not replace "stored as", nor clear it as a state left behind."""
    page, problems = await open_page(browser, dashboard, PANEL)
    await log_in(page, dashboard.token)
    await expect_state(page, "IDLE")
    stored_shown = asyncio.Event()

    async def answer_late(route: Any) -> None:
        body = route.request.post_data or ""
        response = await route.fetch()
        if "if_new" not in body:  # the copy's capture: its answer held until its end shows
            await stored_shown.wait()
        await route.fulfill(response=response)

    await page.route("**/create-workpiece", answer_late)
    answers = iter([("prompt", "late"), ("confirm", None)])

    async def answer(dialog: Any) -> None:
        kind, text = next(answers)
        assert dialog.type == kind, (dialog.type, dialog.message)
        await (dialog.accept(text) if kind == "prompt" else dialog.accept())

    page.on("dialog", answer)
    await page.click('[data-command="create-workpiece"]')
    await expect(page.locator("#message")).to_contain_text("workpiece late stored as")
    async with page.expect_response("**/create-workpiece") as held:
        stored_shown.set()
    assert (await held.value).status == 202
    await expect_state(page, "IDLE")
    await page.evaluate("() => new Promise(r => setTimeout(r, 300))")  # the late answer applied
    await expect(page.locator("#message")).to_contain_text("workpiece late stored as")
    assert problems == []
