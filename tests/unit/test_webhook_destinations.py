"""The webhook destination policy: the cell itself, loopback, link-local and unspecified
addresses are refused at load, naming the webhook and never its path, query or secret,
unless `webhook_allowed_networks` allows them (so `http://127.0.0.1:8000/estop` and
`http://169.254.169.254/` are never posted to)."""

from __future__ import annotations

import ipaddress
import re
import socket

import httpcore
import psutil
import pytest
from pydantic import ValidationError

from server.security import destinations
from server.security.destinations import DestinationRefused, GuardedBackend
from server.settings.load import SettingsRefused, load_settings
from server.settings.model import Settings

SECRET = "0123456789abcdef-secret"
SECRET_PATH = "/estop/path-token-SHOULD-NOT-SHOW?key=query-SHOULD-NOT-SHOW"


def webhook(url: str, name: str = "plc") -> dict:
    return {"name": name, "url": url, "secret": SECRET}


def own_address() -> str:
    """An address of one of this host's interfaces that is not loopback or link-local."""
    for addresses in psutil.net_if_addrs().values():
        for entry in addresses:
            if entry.family in (socket.AF_INET, socket.AF_INET6):
                address = ipaddress.ip_address(entry.address.split("%", 1)[0])
                if not (address.is_loopback or address.is_link_local):
                    return str(address)
    pytest.fail("this host has no address but loopback and link-local to test with")


REFUSED = [
    ("http://127.0.0.1:8000", "loopback"),
    ("http://127.1.2.3", "loopback"),
    ("http://localhost:8000", "loopback"),
    ("http://LocalHost.:8000", "loopback"),
    ("http://cell.localhost", "loopback"),
    ("http://[::1]:8000", "loopback"),
    ("http://[::ffff:127.0.0.1]:8000", "loopback"),
    ("http://169.254.169.254", "link-local"),
    ("http://[fe80::1]", "link-local"),
    ("http://0.0.0.0:8000", "unspecified"),
    ("http://[::]:8000", "unspecified"),
]


@pytest.mark.parametrize(("base", "kind"), REFUSED)
def test_a_webhook_to_a_refused_address_is_refused_at_load_naming_it(base: str, kind: str) -> None:
    with pytest.raises(ValidationError) as refused:
        Settings(webhooks=[webhook(base + SECRET_PATH)])
    text = str(refused.value.errors()[0]["msg"])
    assert "webhook 'plc'" in text and kind in text and "webhook_allowed_networks" in text
    assert "SHOULD-NOT-SHOW" not in text and SECRET not in text


def test_a_webhook_to_the_cells_own_address_is_refused() -> None:
    address = ipaddress.ip_address(own_address())
    host = f"[{address}]" if address.version == 6 else str(address)
    with pytest.raises(ValidationError, match="this host"):
        Settings(webhooks=[webhook(f"http://{host}:8000/estop")])


def test_the_refusal_at_start_names_the_webhook_and_not_its_url(monkeypatch) -> None:
    monkeypatch.setenv(
        "GLUE_APP_WEBHOOKS",
        f'[{{"name": "mes", "url": "http://127.0.0.1:8000{SECRET_PATH}", "secret": "{SECRET}"}}]',
    )
    with pytest.raises(SettingsRefused) as refused:
        load_settings()
    assert "webhook 'mes'" in str(refused.value)
    assert "SHOULD-NOT-SHOW" not in str(refused.value) and SECRET not in str(refused.value)


@pytest.mark.parametrize(("base", "_kind"), REFUSED)
def test_an_allowed_network_lets_the_address_in(base: str, _kind: str) -> None:
    everything = ["0.0.0.0/0", "::/0"]
    [target] = Settings(
        webhooks=[webhook(base + "/hook")], webhook_allowed_networks=everything
    ).webhooks
    assert target.name == "plc"


def test_only_the_allowed_network_is_let_in() -> None:
    Settings(webhooks=[webhook("http://127.0.0.1:9/hook")], webhook_allowed_networks=["127.0.0.1"])
    with pytest.raises(ValidationError, match="loopback"):
        Settings(
            webhooks=[webhook("http://127.0.0.2:9/hook")], webhook_allowed_networks=["127.0.0.1"]
        )


@pytest.mark.parametrize(
    "url", ["https://plant.example/hook", "http://10.1.2.3/hook", "http://[fd12::1]:8080/h"]
)
def test_plant_addresses_and_names_load(url: str) -> None:
    Settings(webhooks=[webhook(url)])


def test_a_typo_in_the_allowed_networks_is_refused_naming_it() -> None:
    with pytest.raises(
        ValidationError, match=re.escape("webhook_allowed_networks: '127.0.0.1/33'")
    ):
        Settings(webhook_allowed_networks=["127.0.0.1/33"])


# --- at delivery: the name resolved, every address checked --------------------------------


async def test_a_name_that_resolves_to_loopback_is_refused_at_connection() -> None:
    """A host name passes the load check; what it resolves to is checked at each connection
    (a DNS answer that changes to 127.0.0.1 later, rebinding, included)."""
    backend = GuardedBackend(())
    with pytest.raises(DestinationRefused, match=re.escape("127.0.0.1, a loopback address")):
        await backend.checked_address("localhost", 80)


async def test_a_name_resolving_into_an_allowed_network_is_connected_to_that_address() -> None:
    backend = GuardedBackend(destinations.parse_networks(["127.0.0.0/8", "::1"]))
    assert ipaddress.ip_address(await backend.checked_address("localhost", 80)).is_loopback


async def test_an_unresolvable_name_is_a_connection_error_not_a_refusal() -> None:
    with pytest.raises(httpcore.ConnectError):
        await GuardedBackend(()).checked_address("no-such-host.invalid", 80)
