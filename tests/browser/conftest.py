"""What every browser test shares: Debian's Chromium, driven by Playwright.

Never `playwright install`: the browser is Debian's package, installed by `make test`.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from playwright.async_api import Browser, async_playwright, expect

CHROMIUM = Path("/usr/bin/chromium")
LAUNCH_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
# How long an assertion on the page waits for what it expects, where the test does not say.
# Playwright's own default (5 s) is a bound a page can miss while the suite's other workers
# keep both cores busy (a message that had not yet changed after 5 s, seen at two workers
# per core under a profiler); a bound on a busy machine, never a performance assertion:
# a passing assertion returns as soon as it holds.
EXPECT_TIMEOUT_MS = 20_000
expect.set_options(timeout=EXPECT_TIMEOUT_MS)


def require_chromium() -> None:
    """Fail, never skip: a missing browser must not pass for a green run."""
    if not CHROMIUM.exists():
        pytest.fail(
            f"{CHROMIUM} is missing: the browser tests need Debian's chromium. "
            "Run `make test`, which installs it (never `playwright install`).",
            pytrace=False,
        )


@pytest.fixture
async def browser() -> AsyncIterator[Browser]:
    require_chromium()
    async with async_playwright() as playwright:
        browser = await playwright.chromium.launch(executable_path=str(CHROMIUM), args=LAUNCH_ARGS)
        try:
            yield browser
        finally:
            await browser.close()
