"""Which address a request comes from: pure functions of an ASGI scope."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from server.security.forwarded import (
    UNKNOWN,
    client_address,
    parse_networks,
    rewritten_by_server,
)
from server.settings.model import Settings

PROXIES = parse_networks(["127.0.0.1", "192.0.2.0/24", "2001:db8::/32"])


def scope(peer: tuple[str, int] | None, *headers: tuple[str, str]) -> dict:
    return {
        "type": "http",
        "client": peer,
        "headers": [(k.lower().encode(), v.encode("latin-1")) for k, v in headers],
    }


PEER = ("127.0.0.1", 50123)


def test_without_trusted_proxies_the_peer_is_the_client_whatever_the_headers_say() -> None:
    request = scope(PEER, ("X-Forwarded-For", "10.1.2.3"), ("Forwarded", "for=10.1.2.3"))
    assert client_address(request, [], "x-forwarded-for") == "127.0.0.1"
    assert client_address(request, [], "forwarded") == "127.0.0.1"


def test_a_peer_that_is_not_a_trusted_proxy_is_not_believed() -> None:
    request = scope(("198.51.100.4", 40000), ("X-Forwarded-For", "10.1.2.3"))
    assert client_address(request, PROXIES, "x-forwarded-for") == "198.51.100.4"


@pytest.mark.parametrize(
    ("chain", "client"),
    [
        ("10.1.1.1", "10.1.1.1"),
        ("10.1.1.1, 203.0.113.5", "203.0.113.5"),  # the leftmost is the client's own word
        ("10.1.1.1, 203.0.113.5, 192.0.2.7", "203.0.113.5"),  # trusted hops skipped
        ("192.0.2.9, 192.0.2.7", "192.0.2.9"),  # every hop trusted: the leftmost
        ("203.0.113.5:8443", "203.0.113.5"),
        ("[2001:db8::1]:80, 2001:0db8:0:0:0:0:0:2", "2001:db8::1"),  # canonical, trusted skipped
        ("10.1.1.1, not-an-address", UNKNOWN),  # never believed, never a pass either
        ("", "127.0.0.1"),  # an empty header: the peer
    ],
)
def test_a_trusted_proxys_chain_gives_its_rightmost_untrusted_hop(chain: str, client: str) -> None:
    request = scope(PEER, ("X-Forwarded-For", chain))
    assert client_address(request, PROXIES, "x-forwarded-for") == client


def test_every_occurrence_of_the_header_counts_in_order() -> None:
    request = scope(PEER, ("X-Forwarded-For", "10.1.1.1"), ("X-Forwarded-For", "203.0.113.5"))
    assert client_address(request, PROXIES, "x-forwarded-for") == "203.0.113.5"


def test_forwarded_is_read_by_its_for_parameters() -> None:
    request = scope(
        PEER,
        ("Forwarded", 'for=10.1.1.1;proto=http, For="[2a00:cafe::17]:4711";by=192.0.2.7'),
        ("Forwarded", "for=192.0.2.7"),
    )
    assert client_address(request, PROXIES, "forwarded") == "2a00:cafe::17"
    assert client_address(scope(PEER, ("Forwarded", "for=_hidden")), PROXIES, "forwarded") == (
        UNKNOWN
    )


def test_only_the_configured_header_is_read() -> None:
    request = scope(PEER, ("Forwarded", "for=10.3.3.3"), ("X-Forwarded-For", "10.4.4.4"))
    assert client_address(request, PROXIES, "x-forwarded-for") == "10.4.4.4"
    assert client_address(request, PROXIES, "forwarded") == "10.3.3.3"


@pytest.mark.parametrize(
    ("peer", "chain", "rewritten"),
    [
        (("10.1.2.3", 0), "10.1.2.3", True),  # uvicorn: the hop's host, port 0
        (("10.1.2.3", 4444), "10.9.9.9, 10.1.2.3:4444", True),  # the hop's own port
        (("10.1.2.3:x", 0), "10.1.2.3:x", True),  # a hop uvicorn could not split
        (("127.0.0.1", 50123), "10.1.2.3", False),  # a real peer
        (("10.1.2.3", 50123), "10.1.2.3", False),  # a real peer naming itself: harmless
        (None, "10.1.2.3", False),
    ],
)
def test_a_peer_the_server_took_from_x_forwarded_for_is_recognised(
    peer: tuple[str, int] | None, chain: str, rewritten: bool
) -> None:
    assert rewritten_by_server(scope(peer, ("X-Forwarded-For", chain))) is rewritten


def test_a_trusted_proxy_that_is_not_an_address_is_refused_at_load() -> None:
    with pytest.raises(ValidationError, match="trusted_proxies"):
        Settings(trusted_proxies=["10.0.0.0/8", "proxy.example"])
    with pytest.raises(ValidationError, match="forwarded_header"):
        Settings(forwarded_header="x-real-ip")
    assert Settings().trusted_proxies == []
