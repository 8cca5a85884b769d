"""The dashboard's header and order form as a person at a panel meets them, in Chromium.

Signed in as maintenance or admin the header carries one more item (the Set-up link):
at 1024×768 it must still be one row, every label on one line ("Set-up" and "Sign
out" are not broken over two lines, the brand not wrapped) and STOP in view. The order
form's fields are typed into on a touch panel: each at least 44 px tall, as every other
control. Checked at 1024×768, 1366×768 and 1920×1080 for each role that sees them.
"""

from __future__ import annotations

from playwright.async_api import Browser, Page

from tests.browser.test_dashboard import (  # noqa: F401 - the fixture is used by name
    Dashboard,
    dashboard,
    expect_state,
)
from tests.browser.test_roles import SIZES, in_view, sign_in

TOUCH_PX = 44
HEADER = ("#app .brand", "#nav-setup", "#link", "#clock", "#logout", "#estop")


async def lines(page: Page, selector: str) -> int:
    """How many lines the element's text takes (a wrapped label takes two)."""
    return await page.locator(selector).evaluate(
        """(el) => { const walker = document.createTreeWalker(el, NodeFilter.SHOW_TEXT);
                     const tops = new Set();
                     for (let node = walker.nextNode(); node; node = walker.nextNode()) {
                       const range = document.createRange(); range.selectNodeContents(node);
                       for (const r of range.getClientRects()) {
                         if (r.width > 0) tops.add(Math.round(r.top));
                       }
                     }
                     return tops.size; }"""
    )


async def visible(page: Page, selector: str) -> bool:
    return await page.locator(selector).evaluate("(el) => el.offsetParent !== null")


async def test_the_header_is_one_row_of_unbroken_labels_for_every_role(
    dashboard: Dashboard,  # noqa: F811 - the fixture imported above
    browser: Browser,
) -> None:
    for role in ("operator", "maintenance", "admin"):
        created = await dashboard.rig.api.post(
            "/tokens", json={"name": f"line 3 {role}", "role": role}
        )
        assert created.status_code == 201, created.text
        page, problems = await sign_in(browser, dashboard, created.json()["token"])
        await expect_state(page, "IDLE")
        for size in SIZES:
            await page.set_viewport_size(size)
            shown = [s for s in HEADER if await visible(page, s)]
            assert "#estop" in shown and "#logout" in shown, (role, size, shown)
            if role != "operator":
                assert "#nav-setup" in shown, (role, size)
            for selector in shown:
                assert await lines(page, selector) == 1, (role, size, selector)
            assert await in_view(page, "#estop"), (role, size)
            for field in ("#order-workpiece", "#order-quantity"):
                box = await page.locator(field).bounding_box()
                assert box is not None and box["height"] >= TOUCH_PX, (role, size, field, box)
        assert not problems, (role, problems)
        await page.context.close()
