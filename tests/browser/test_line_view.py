"""The line view in Debian's Chromium against Debian's mosquitto: the page is served by
`python -m server.line.view` (a process), and reads the broker's WebSocket listener with
the vendored MQTT.js. Three stand-in cells publish the topic contract with paho
(tests/line_publisher.py); one of them holds its connection with a last will and a
one-second keep-alive and is then frozen (SIGSTOP: the socket stays open, as with a
hung or unplugged cell), so `offline` comes from the broker's keep-alive.

Screenshots go to test-artifacts/screenshots/line-view-*.png.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest
from playwright.async_api import Browser, ConsoleMessage, Page, expect

from server.line.broker import BrokerPorts
from tests.line_broker_fixture import running_broker
from tests.line_publisher import publish_cell, state_message
from tests.processes import ROOT, environment, stop, wait_answering
from tests.serving import free_port

SHOTS = ROOT / "test-artifacts" / "screenshots"
SCREENS = {"panel": {"width": 1920, "height": 1080}, "laptop": {"width": 1280, "height": 800}}
PROGRESS = {"run_id": "r-1", "waypoint": 4, "total": 10, "fraction": 0.4}
# The will fires after 1.5 keep-alives of silence; this only bounds a broken run.
OFFLINE_WAIT_MS = 30_000


@dataclass
class Line:
    broker: BrokerPorts
    url: str
    frozen_cell: subprocess.Popen[str]


@pytest.fixture
def line(tmp_path: Path) -> Iterator[Line]:
    with running_broker(tmp_path / "broker") as broker:
        port = free_port()
        log = (tmp_path / "line-view.log").open("w")
        ws = ["--broker-ws", broker.websocket_url]
        frozen = ["--cell", "cell-3", "--keepalive", "1"]
        view = subprocess.Popen(
            [sys.executable, "-m", "server.line.view", "--port", str(port), *ws],
            stdout=log,
            stderr=subprocess.STDOUT,
            text=True,
            env=environment(),
            cwd=ROOT,
        )
        cell_3 = subprocess.Popen(
            [sys.executable, "-m", "tests.line_publisher", "--port", str(broker.mqtt), *frozen],
            stdout=subprocess.PIPE,
            text=True,
            env=environment(),
            cwd=ROOT,
        )
        try:
            assert cell_3.stdout is not None and cell_3.stdout.readline().strip() == "published"
            url = f"http://127.0.0.1:{port}/"
            wait_answering(view, url, 60, log=tmp_path / "line-view.log")  # a hang guard
            yield Line(broker, url, cell_3)
        finally:
            if cell_3.poll() is None:
                os.kill(cell_3.pid, signal.SIGKILL)  # works on a stopped process too
                cell_3.wait()
            stop(view)
            log.close()


class PageErrors(list[str]):
    """Script errors and console errors (a CSP refusal of the broker would be one)."""

    def watch(self, page: Page) -> None:
        page.on("pageerror", lambda error: self.append(f"page error: {error}"))
        page.on("console", self.on_console)

    def on_console(self, message: ConsoleMessage) -> None:
        if message.type == "error":
            self.append(f"console error: {message.text}")


@pytest.fixture
async def page(browser: Browser, line: Line) -> AsyncIterator[tuple[Page, PageErrors]]:
    context = await browser.new_context(viewport=SCREENS["panel"])
    errors = PageErrors()
    page = await context.new_page()
    errors.watch(page)
    try:
        yield page, errors
    finally:
        await context.close()


def cell(page: Page, cell_id: str, part: str):  # type: ignore[no-untyped-def]
    return page.locator(f'[data-cell="{cell_id}"] {part}')


async def fits(page: Page) -> None:
    """Every card whole on the screen, nothing to scroll."""
    overflow = await page.evaluate(
        """() => {
          const root = document.documentElement, main = document.getElementById("cells");
          const out = [...document.querySelectorAll(".cell")].filter((c) => {
            const r = c.getBoundingClientRect();
            return r.left < 0 || r.top < 0 || r.right > innerWidth || r.bottom > innerHeight;
          }).map((c) => c.dataset.cell);
          return {out, scrollX: root.scrollWidth > root.clientWidth,
                  scrollMain: main.scrollHeight > main.clientHeight,
                  cards: document.querySelectorAll(".cell").length};
        }"""
    )
    assert overflow == {"out": [], "scrollX": False, "scrollMain": False, "cards": 3}, overflow


async def test_the_line_view_shows_every_cell_live_and_a_frozen_cell_goes_offline(
    page: tuple[Page, PageErrors], line: Line
) -> None:
    page_, errors = page
    run = {"run_id": "r-1", "workpiece_id": "wp-7"}
    state_1 = state_message("cell-1", "EXECUTING_TRAJECTORY", **run)
    publish_cell(line.broker.mqtt, "cell-1", state_1, 0.75)
    stopped = {"code": "ESTOP", "message": "stop pressed at the cell"}
    publish_cell(
        line.broker.mqtt, "cell-2", state_message("cell-2", "ERROR", stop_reason=stopped), None
    )
    await page_.goto(line.url)
    await expect(page_.locator("#broker")).to_have_attribute("data-connected", "true")
    # The retained state of all three, read on connecting.
    await expect(cell(page_, "cell-1", ".state")).to_have_text("EXECUTING_TRAJECTORY")
    await expect(cell(page_, "cell-1", ".oee")).to_have_text("75.0 %")
    await expect(cell(page_, "cell-1", ".run")).to_have_text("r-1")
    await expect(cell(page_, "cell-2", ".state")).to_have_text("ERROR")
    await expect(cell(page_, "cell-2", ".stop")).to_have_text("ESTOP: stop pressed at the cell")
    await expect(cell(page_, "cell-3", ".state")).to_have_text("IDLE")
    await expect(cell(page_, "cell-3", ".oee")).to_have_text("50.0 %")
    for cell_id in ("cell-1", "cell-2", "cell-3"):
        await expect(cell(page_, cell_id, ".link")).to_have_text("online")
    assert await page_.locator(".cell").evaluate_all("cs => cs.map(c => c.dataset.cell)") == [
        "cell-1",
        "cell-2",
        "cell-3",
    ]
    # Live: a progress message of cell-1's run.
    publish_cell(line.broker.mqtt, "cell-1", state_1, 0.75, PROGRESS)
    await expect(cell(page_, "cell-1", ".progress")).to_have_text("40 % (4/10)")
    width = await cell(page_, "cell-1", ".bar > span").evaluate("e => e.style.width")
    assert width == "40%"
    for name, screen in SCREENS.items():
        await page_.set_viewport_size(screen)
        await fits(page_)
        SHOTS.mkdir(parents=True, exist_ok=True)
        await page_.screenshot(path=str(SHOTS / f"line-view-{name}.png"))
    # cell-3 hangs with its connection open: the broker's keep-alive runs out, its will
    # (`offline`) arrives; the other cells stay as they were.
    os.kill(line.frozen_cell.pid, signal.SIGSTOP)
    await expect(cell(page_, "cell-3", ".link")).to_have_text("offline", timeout=OFFLINE_WAIT_MS)
    await expect(page_.locator('[data-cell="cell-3"]')).to_have_attribute("data-online", "false")
    await expect(cell(page_, "cell-3", ".state")).to_have_attribute("data-stale", "true")
    await expect(cell(page_, "cell-1", ".link")).to_have_text("online")
    await page_.screenshot(path=str(SHOTS / "line-view-offline.png"))
    assert errors == []


def test_the_page_may_connect_to_its_broker_and_nowhere_else(line: Line) -> None:
    answer = httpx.get(line.url)
    csp = answer.headers["content-security-policy"]
    assert re.search(rf"connect-src 'self' {re.escape(line.broker.websocket_url)};", csp), csp
    assert "script-src 'self'" in csp
    config = httpx.get(line.url + "line-config.json").json()
    assert config == {"broker": line.broker.websocket_url, "prefix": "glue"}
    vendored = httpx.get(line.url + "hmi/vendor/mqtt-5.16.0/mqtt.esm.js")
    assert vendored.status_code == 200 and "javascript" in vendored.headers["content-type"]
