"""Which address a request comes from: its peer, unless a trusted proxy says otherwise.

`X-Forwarded-For` and `Forwarded` are written by whoever sends the request.
Believed from anyone, they let a client put any address in the audit trail
and walk past `trusted_networks`. So they are read only when the peer is one
of `trusted_proxies` (none by default), and only the one header those proxies
set (`forwarded_header`): a proxy that appends to X-Forwarded-For passes a
client's own `Forwarded` through untouched, and the other way round.

Each proxy appends the address it received the request from, so the list
reads client, proxy 1, proxy 2, ...; everything left of the last address a
trusted proxy wrote is the client's own word. The client is therefore the
rightmost hop that is not itself a trusted proxy (the leftmost hop if every
one is), never simply the leftmost.

Servers rewrite too: uvicorn, by default, replaces the peer with an address
from X-Forwarded-For when the peer is on loopback, before the app sees the
request. `python -m server` turns that off (`server/__main__.py:
uvicorn_options`); `rewritten_by_server` recognises a request it was done to
anyway (the peer is then one of the header's own hops, on a port no TCP peer
has or the one the header names), so the gate can refuse it instead of
believing it, however the app is served.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable, Sequence
from typing import Literal

from starlette.types import Scope

Network = ipaddress.IPv4Network | ipaddress.IPv6Network
HeaderName = Literal["x-forwarded-for", "forwarded"]
UNKNOWN = "unknown"  # a hop that is not an address ("unknown", "_hidden", garbage)


def parse_networks(entries: Iterable[str]) -> list[Network]:
    """CIDRs or single addresses as networks; ValueError naming a bad entry."""
    networks = []
    for entry in entries:
        try:
            networks.append(ipaddress.ip_network(entry.strip(), strict=False))
        except ValueError:
            raise ValueError(f"{entry!r} is not an IP address or network (CIDR)") from None
    return networks


def _split_host_port(value: str) -> tuple[str, int | None]:
    """`1.2.3.4`, `1.2.3.4:80`, `[::1]`, `[::1]:80` or `::1` → (host, port)."""
    value = value.strip().strip('"')
    if value.startswith("["):
        host, _, rest = value[1:].partition("]")
        port = rest[1:] if rest.startswith(":") else ""
        return host, int(port) if port.isdigit() else None
    if value.count(":") == 1:
        host, _, port = value.partition(":")
        return host, int(port) if port.isdigit() else None
    return value, None


def _address(value: str) -> str:
    """The hop's address in canonical form, or UNKNOWN if it is none."""
    host, _ = _split_host_port(value)
    try:
        return str(ipaddress.ip_address(host))
    except ValueError:
        return UNKNOWN


def _header_values(scope: Scope, name: bytes) -> list[str]:
    return [v.decode("latin-1") for k, v in scope.get("headers") or () if k == name]


def forwarded_hops(scope: Scope, header: HeaderName) -> list[str]:
    """The raw hops the header lists, client first, over every occurrence of it."""
    values = _header_values(scope, header.encode("ascii"))
    if header == "x-forwarded-for":
        return [hop.strip() for value in values for hop in value.split(",") if hop.strip()]
    hops = []
    for value in values:  # Forwarded: for=a;proto=http, for="[::1]:80" (RFC 7239)
        for element in value.split(","):
            pairs = (pair.strip().partition("=") for pair in element.split(";"))
            hops += [v.strip() for k, _, v in pairs if k.strip().lower() == "for" and v.strip()]
    return hops


def _trusted(address: str, proxies: Sequence[Network]) -> bool:
    if address == UNKNOWN:
        return False
    ip = ipaddress.ip_address(address)
    return any(ip in network for network in proxies)


def peer_of(scope: Scope) -> str | None:
    client = scope.get("client")
    return client[0] if client else None


def client_address(scope: Scope, proxies: Sequence[Network], header: HeaderName) -> str | None:
    """The request's client: its peer, or the rightmost untrusted hop a trusted peer forwarded."""
    peer = peer_of(scope)
    if not proxies or peer is None or not _trusted(_address(peer), proxies):
        return peer
    hops = [_address(hop) for hop in forwarded_hops(scope, header)]
    for hop in reversed(hops):
        if not _trusted(hop, proxies):
            return hop
    return hops[0] if hops else peer


def rewritten_by_server(scope: Scope) -> bool:
    """Whether the server in front already replaced the peer with an X-Forwarded-For hop.

    uvicorn's proxy headers set the peer to a hop's host and port, 0 when the
    hop names none; a real TCP peer never has port 0, nor does a proxy list
    the very host and port it is connecting from.
    """
    client = scope.get("client")
    if not client:
        return False
    host, port = client[0], client[1]
    for hop in forwarded_hops(scope, "x-forwarded-for"):
        hop_host, hop_port = _split_host_port(hop)
        # uvicorn keeps a hop it cannot split ("1.2.3.4:x") whole, with port 0.
        if host in (hop_host, hop) and port in (0, hop_port):
            return True
    return False
