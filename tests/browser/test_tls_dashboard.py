"""The dashboard over https, in Debian's Chromium.

The page is served from the same origin as the API, so over https its requests are
https and its live view is wss (clients/hmi/live.js builds the WebSocket address
from `location.protocol`). The server serves a certificate from a CA made in the
test (tests/tls_pki.py). Chromium is not told to ignore certificate errors: it is
given the SHA-256 of the server key's SubjectPublicKeyInfo
(`--ignore-certificate-errors-spki-list`), so it accepts that one key and no other;
pinned to another key, the same page is refused (ERR_CERT_AUTHORITY_INVALID), which
the test checks first. Installing the test CA in an NSS database would need certutil
(libnss3-tools), which the suite does not install.
"""

from __future__ import annotations

import base64
import hashlib
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from playwright.async_api import Error as PlaywrightError
from playwright.async_api import async_playwright, expect

from server.bootstrap.cell import Cell
from server.core.worker.devices import CellDevices
from server.settings.model import Settings
from tests.browser.conftest import CHROMIUM, LAUNCH_ARGS, require_chromium
from tests.conftest import demo_stores
from tests.fakes import FakeCamera, FakeGlue, FakeRobot
from tests.serving import serve
from tests.tls_pki import Pki, make_pki


def spki_sha256(cert_file: Path) -> str:
    """base64 of the SHA-256 of the certificate's public key (SubjectPublicKeyInfo)."""
    key = x509.load_pem_x509_certificate(cert_file.read_bytes()).public_key()
    der = key.public_bytes(
        serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    )
    return base64.b64encode(hashlib.sha256(der).digest()).decode()


@pytest.fixture
async def https_cell(tmp_path: Path) -> AsyncIterator[tuple[str, Path, Pki]]:
    pki = make_pki(tmp_path / "pki")
    settings = Settings(
        data_path=tmp_path / "data",
        tls_cert_file=pki.cert_file,
        tls_key_file=pki.key_file,
        emergency_stop_timeout=0.5,
    )
    demo_stores(settings.data_path)
    cell = Cell(settings, devices=CellDevices(FakeRobot(speed_factor=5), FakeGlue(), FakeCamera()))
    async with serve(cell) as url:
        yield url, settings.data_path, pki


async def test_the_dashboard_logs_in_and_goes_live_over_https_and_wss(https_cell) -> None:
    url, data, pki = https_cell
    assert url.startswith("https://")
    token = (data / "admin.token").read_text().strip()
    require_chromium()
    async with async_playwright() as playwright:
        # Pinned to another key: the flag is a pin, not a way around the check.
        other = make_pki(data.parent / "other")
        wrong_pin = f"--ignore-certificate-errors-spki-list={spki_sha256(other.cert_file)}"
        untrusting = await playwright.chromium.launch(
            executable_path=str(CHROMIUM), args=[*LAUNCH_ARGS, wrong_pin]
        )
        try:
            page = await untrusting.new_page()
            with pytest.raises(PlaywrightError, match="ERR_CERT_AUTHORITY_INVALID"):
                await page.goto(url + "/")
        finally:
            await untrusting.close()
        pinned = f"--ignore-certificate-errors-spki-list={spki_sha256(pki.cert_file)}"
        browser = await playwright.chromium.launch(
            executable_path=str(CHROMIUM), args=[*LAUNCH_ARGS, pinned]
        )
        try:
            page = await browser.new_page()
            sockets: list[str] = []
            page.on("websocket", lambda socket: sockets.append(socket.url))
            await page.goto(url + "/")
            await page.fill("#token-input", token)
            await page.click("#login-button")
            await expect(page.locator("#app")).to_be_visible()
            await expect(page.locator("#link")).to_have_attribute(
                "data-live", "true", timeout=15_000
            )
            await expect(page.locator("#state")).to_have_attribute(
                "data-state", "IDLE", timeout=15_000
            )
            assert sockets and all(s.startswith("wss://127.0.0.1:") for s in sockets), sockets
        finally:
            await browser.close()
