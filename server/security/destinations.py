"""Where a webhook may post: never the cell itself, loopback, link-local or nowhere, unless allowed.

Why a policy at all: a webhook is a request the cell makes on someone's say-so. Set to
`http://127.0.0.1:8000/estop` it posts to the cell's own API; set to
`http://169.254.169.254/` it reaches a cloud host's metadata service, which hands
out credentials; an unspecified address (0.0.0.0, ::) is this host too on Linux. So
loopback (127.0.0.0/8, ::1), link-local (169.254.0.0/16, fe80::/10), unspecified
(0.0.0.0/8, ::) and the cell's own addresses are refused, unless a network in the
`webhook_allowed_networks` setting holds the address (a receiver on the same host, in
a lab or a test, is allowed that way, explicitly). Plant networks (10/8, 192.168/16,
...) are where receivers live, so they are not refused.

Checked twice: at load for a URL whose host is an address or `localhost` (the
refusal names the webhook, never its path or query, which may be secret), and at
every connection, after the host name is resolved, on the address connected to
(`GuardedBackend`): a name that resolves into a refused range, now or after a DNS
change (rebinding), is refused then, and the connection goes to the very address
that was checked, so a second lookup cannot swap it. The lookup runs in the loop's
resolver thread, never blocking the event loop.
"""

from __future__ import annotations

import asyncio
import functools
import ipaddress
import socket
import ssl
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any

import httpcore

if TYPE_CHECKING:  # httpx is imported where a webhook is sent: the settings need none of it
    import httpx

IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address
IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network

REFUSED_RANGES: tuple[tuple[str, IPNetwork], ...] = tuple(
    (kind, ipaddress.ip_network(network))
    for kind, network in (
        ("loopback", "127.0.0.0/8"),
        ("loopback", "::1/128"),
        ("link-local", "169.254.0.0/16"),
        ("link-local", "fe80::/10"),
        ("unspecified", "0.0.0.0/8"),
        ("unspecified", "::/128"),
    )
)
SETTING = "webhook_allowed_networks"
# An address no host has (TEST-NET-2, RFC 5737): if it can be bound, the kernel binds any
# address (ip_nonlocal_bind) and a bind says nothing about which addresses are this host's.
_NOBODYS_ADDRESS = "198.51.100.254"


class DestinationRefused(Exception):
    """A webhook's address is one the policy refuses; final, never retried."""


def parse_networks(entries: Iterable[str]) -> tuple[IPNetwork, ...]:
    """The allowed networks (CIDR or single addresses); ValueError naming a bad entry."""
    networks = []
    for entry in entries:
        try:
            networks.append(ipaddress.ip_network(entry.strip(), strict=False))
        except ValueError:
            raise ValueError(
                f"{SETTING}: {entry!r} is not an IP address or network (CIDR)"
            ) from None
    return tuple(networks)


def refusal(address: IPAddress, allowed: Sequence[IPNetwork] = ()) -> str | None:
    """Why the policy refuses `address` ("a loopback address", ...), or None when it may."""
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped  # ::ffff:127.0.0.1 is 127.0.0.1
    if any(address.version == n.version and address in n for n in allowed):
        return None
    for kind, network in REFUSED_RANGES:
        if address.version == network.version and address in network:
            return f"{'an' if kind[0] in 'aeiou' else 'a'} {kind} address"
    if is_own_address(address):
        return "an address of this host (the cell itself)"
    return None


def is_own_address(address: IPAddress) -> bool:
    """Whether `address` is one of this host's: only a local address can be bound."""
    if not _bind_tells_own_addresses():
        return False
    return _binds(str(address), socket.AF_INET6 if address.version == 6 else socket.AF_INET)


@functools.cache
def _bind_tells_own_addresses() -> bool:
    return not _binds(_NOBODYS_ADDRESS, socket.AF_INET)


def _binds(address: str, family: socket.AddressFamily) -> bool:
    try:
        with socket.socket(family, socket.SOCK_DGRAM) as probe:
            probe.bind((address, 0))
    except OSError:
        return False
    return True


def load_refusal(host: str, allowed: Sequence[IPNetwork] = ()) -> str | None:
    """Why a URL's host is refused at load (an address, or `localhost`), or None.

    A host name is not resolved here (a receiver's DNS may be down while the cell
    starts): it is checked at each connection instead (`GuardedBackend`).
    """
    name = host.strip("[]").rstrip(".").lower()
    try:
        address = ipaddress.ip_address(name.split("%", 1)[0])
    except ValueError:
        if name == "localhost" or name.endswith(".localhost"):
            address = ipaddress.ip_address("127.0.0.1")  # RFC 6761: always loopback
        else:
            return None
    return refusal(address, allowed)


class GuardedBackend(httpcore.AsyncNetworkBackend):
    """httpcore's network backend, resolving and checking each address before it connects."""

    def __init__(self, allowed: Sequence[IPNetwork]) -> None:
        self._allowed = tuple(allowed)
        self._inner = httpcore.AnyIOBackend()

    async def connect_tcp(
        self,
        host: str,
        port: int,
        timeout: float | None = None,
        local_address: str | None = None,
        socket_options: Iterable[Any] | None = None,
    ) -> httpcore.AsyncNetworkStream:
        address = await self.checked_address(host, port)
        return await self._inner.connect_tcp(address, port, timeout, local_address, socket_options)

    async def checked_address(self, host: str, port: int) -> str:
        """The address to connect to; DestinationRefused if any address `host` has is refused.

        Every address is checked, not only the first: a name that answers both a plant
        address and 127.0.0.1 is refused rather than connected by luck.
        """
        loop = asyncio.get_running_loop()
        try:
            found = await loop.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        except OSError as exc:
            raise httpcore.ConnectError(f"cannot resolve the webhook's host: {exc}") from None
        addresses = [str(info[4][0]) for info in found]
        for text in addresses:
            why = refusal(ipaddress.ip_address(text.split("%", 1)[0]), self._allowed)
            if why is not None:
                raise DestinationRefused(
                    f"its host resolves to {text}, {why}: refused by the webhook destination "
                    f"policy (allow it with {SETTING})"
                )
        return addresses[0]

    async def connect_unix_socket(self, *args: Any, **kwargs: Any) -> httpcore.AsyncNetworkStream:
        raise DestinationRefused("a webhook never posts to a Unix socket")

    async def sleep(self, seconds: float) -> None:
        await self._inner.sleep(seconds)


def guarded_transport(allowed: Sequence[IPNetwork]) -> httpx.AsyncHTTPTransport:
    """An httpx transport whose every connection goes through `GuardedBackend`.

    httpx takes no network backend of its own, so its pool is replaced by an httpcore
    pool built as httpx builds it (TLS verified against the system's CAs, no proxy).
    """
    import httpx

    transport = httpx.AsyncHTTPTransport(trust_env=False)
    context: ssl.SSLContext = httpx.create_ssl_context(trust_env=False)
    transport._pool = httpcore.AsyncConnectionPool(
        ssl_context=context, network_backend=GuardedBackend(allowed)
    )
    return transport
