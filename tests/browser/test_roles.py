"""The dashboard for each role, in Chromium at the panel sizes, against the real server.

Signed in as viewer, operator, maintenance or admin, the page offers only what the
token's role may do (GET /me): the commands it may never send are not buttons, the
Set-up link only for a role that may open it. After a STOP, a role that cannot reset
is told whom to call, in words; no message carries an HTTP status, and the stop reason
names the token that pressed STOP. One rig and one browser for the whole module.
"""

from __future__ import annotations

import re
from typing import Any

from playwright.async_api import Browser, Page, expect

from tests.browser.test_dashboard import (  # noqa: F401 - the fixture is used by name
    COMMANDS,
    Dashboard,
    Problems,
    dashboard,
    expect_live,
    expect_state,
)

SIZES = (
    {"width": 1024, "height": 768},
    {"width": 1366, "height": 768},
    {"width": 1920, "height": 1080},
)
# The commands each role may send, and those of them IDLE allows.
ROLE_COMMANDS = {
    "viewer": set(),
    "operator": {"start", "pause", "resume", "cancel", "create-workpiece"},
    "maintenance": set(COMMANDS),
    "admin": set(COMMANDS),
}
IDLE = {"start", "calibrate-robot", "calibrate-camera", "create-workpiece"}
CALL_MAINTENANCE = "Call maintenance to reset: needs the maintenance role"
HTTP_STATUS = re.compile(r"\b(200|201|202|400|403|404|409|422|503)\b")


async def sign_in(browser: Browser, cell: Dashboard, token: str) -> tuple[Page, Problems]:
    context = await browser.new_context(viewport=SIZES[0])
    page = await context.new_page()
    problems = Problems().watch(page)
    await page.goto(cell.url + "/")
    await page.fill("#token-input", token)
    await page.click("#login-button")
    await expect(page.locator("#app")).to_be_visible()
    await expect_live(page)
    return page, problems


async def in_view(page: Page, selector: str) -> bool:
    """Whether the element is wholly inside the viewport (the page is never scrolled)."""
    return await page.locator(selector).evaluate(
        """(el) => { const r = el.getBoundingClientRect();
                     return r.top >= 0 && r.left >= 0 && r.bottom <= innerHeight + 0.5
                       && r.right <= innerWidth + 0.5 && r.width > 0; }"""
    )


async def expect_offered(page: Page, role: str, enabled: set[str]) -> None:
    """The role's commands are buttons, `enabled` of them live; the others are not shown."""
    for name in COMMANDS:
        button = page.locator(f'[data-command="{name}"]')
        if name not in ROLE_COMMANDS[role]:
            await expect(button, f"{role}: {name} is not offered").to_be_hidden()
        elif name in enabled:
            await expect(button, f"{role}: {name} is live").to_be_enabled()
        else:
            await expect(button, f"{role}: {name} is not live").to_be_disabled()


async def test_each_role_is_offered_what_it_may_do_and_told_whom_to_call(
    dashboard: Dashboard,  # noqa: F811 - the fixture imported above
    browser: Browser,
) -> None:
    pages: dict[str, tuple[Page, Problems]] = {}
    for role in ROLE_COMMANDS:
        created = await dashboard.rig.api.post(
            "/tokens", json={"name": f"line 3 {role}", "role": role}
        )
        assert created.status_code == 201, created.text
        pages[role] = await sign_in(browser, dashboard, created.json()["token"])

    for role, (page, _) in pages.items():
        await expect_state(page, "IDLE")
        await expect(page.locator("#who")).to_have_text(f"line 3 {role} · {role}")
        setup = page.locator("#nav-setup")
        if role in ("maintenance", "admin"):
            await expect(setup).to_be_visible()
        else:
            await expect(setup).to_be_hidden()
        for size in SIZES:
            await page.set_viewport_size(size)
            await expect_offered(page, role, IDLE & ROLE_COMMANDS[role])
            for name in IDLE & ROLE_COMMANDS[role]:
                assert await in_view(page, f'[data-command="{name}"]'), (role, size, name)
            assert await in_view(page, "#estop"), (role, size)

    # The operator presses STOP: the reason names its token, the message has no status.
    operator, _ = pages["operator"]
    await operator.click("#estop")
    for role, (page, _) in pages.items():
        await expect_state(page, "ERROR")
        await expect(page.locator("#fault-message")).to_contain_text(
            "emergency stop by line 3 operator"
        )
        call = page.locator("#fault-call")
        for size in SIZES:
            await page.set_viewport_size(size)
            await expect_offered(page, role, {"reset"} & ROLE_COMMANDS[role])
            if role in ("viewer", "operator"):
                await expect(call).to_have_text(CALL_MAINTENANCE)
                assert await in_view(page, "#fault-call"), (role, size)
            else:
                await expect(call).to_be_hidden()
    message = await operator.locator("#message").text_content() or ""
    assert message and not HTTP_STATUS.search(message), message

    # Maintenance resets from its page; the operator's words go with the stop.
    maintenance, _ = pages["maintenance"]
    await maintenance.click('[data-command="reset"]')
    for role, (page, problems) in pages.items():
        await expect_state(page, "IDLE")
        await expect(page.locator("#fault-call")).to_be_hidden()
        assert not problems, (role, problems)
    # The STOP's answer described the stop: gone once the cell left ERROR.
    await expect(operator.locator("#message")).to_be_hidden()

    # The operator captures the part on the table: asked its name, then told it is the
    # stored demo part and asked before a copy is stored. No, then yes.
    library = dashboard.rig.api
    count = len((await library.get("/workpieces")).json()["workpieces"])
    answers = iter(
        [("prompt", "bracket"), ("confirm", None), ("prompt", "bracket"), ("confirm", "")]
    )
    asked: list[str] = []

    async def answer(dialog: Any) -> None:
        kind, text = next(answers)
        assert dialog.type == kind, (dialog.type, dialog.message)
        asked.append(dialog.message)
        await (dialog.accept(text) if text is not None else dialog.dismiss())

    operator.on("dialog", answer)
    await operator.click('[data-command="create-workpiece"]')
    await expect(operator.locator("#message")).to_contain_text("not stored: the part is")
    assert "matches" in asked[1] and "(demo)" in asked[1] and 'as "bracket"' in asked[1], asked
    assert len((await library.get("/workpieces")).json()["workpieces"]) == count
    await operator.click('[data-command="create-workpiece"]')
    await expect(operator.locator("#message")).to_contain_text("workpiece bracket stored as")
    assert len((await library.get("/workpieces")).json()["workpieces"]) == count + 1
