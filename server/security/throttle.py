"""Bad tokens per client address: after too many, the address waits (429, Retry-After).

Why: a token's secret is far too long to guess, but each wrong guess costs a
hash, an answer, a log line and an audit row, and nothing stopped a client
from sending thousands a second. After `limit` bad tokens or tickets within
`window` seconds an address is locked out for `lockout` seconds: the access
gate answers its requests 429 with Retry-After before it looks at any token,
the right one included (a guess that succeeds would otherwise be told apart).
The e-stop is never locked out (server/api/access.py decides that).

The address is the one the gate computes (the peer, or what a trusted proxy
forwarded). IPv6 clients are counted per /64, the block one host is usually
given, so a host cannot dodge the count by changing its low bits. The table
is bounded: at `max_addresses` the address whose last failure is oldest is
forgotten first, so a flood from many addresses costs memory up to the bound
and no more.

Pure: the caller passes the time (`time.monotonic()` in the server).
"""

from __future__ import annotations

import ipaddress
import math
from collections import OrderedDict, deque
from dataclasses import dataclass, field

MAX_ADDRESSES = 4096  # addresses remembered at once; each holds at most `limit` times


@dataclass(slots=True)
class _Record:
    failures: deque[float] = field(default_factory=deque)  # the last `limit` failure times
    locked_until: float = 0.0


def client_key(address: str) -> str:
    """What is counted: an IPv6 address's /64 (an IPv4-mapped one as IPv4), else the address."""
    if ":" not in address:  # IPv4, or `unknown`: as it is, with no parsing on every request
        return address
    try:
        parsed = ipaddress.IPv6Address(address)
    except ValueError:
        return address
    if parsed.ipv4_mapped is not None:
        return str(parsed.ipv4_mapped)
    return str(ipaddress.IPv6Network(f"{parsed}/64", strict=False))


class AuthThrottle:
    """Counts bad tokens per address; says how long a locked-out address must wait."""

    def __init__(
        self, limit: int, window: float, lockout: float, max_addresses: int = MAX_ADDRESSES
    ) -> None:
        self.limit = limit
        self.window = window
        self.lockout = lockout
        self.max_addresses = max_addresses
        self._records: OrderedDict[str, _Record] = OrderedDict()  # least recent first

    def retry_after(self, address: str, now: float) -> int | None:
        """Whole seconds `address` must still wait, or None if it is not locked out."""
        if not self._records:  # no bad token lately: the common case costs nothing
            return None
        record = self._records.get(client_key(address))
        if record is None or record.locked_until <= now:
            return None
        return max(1, math.ceil(record.locked_until - now))

    def failed(self, address: str, now: float) -> bool:
        """Count one bad token from `address`; True if that locks it out (now)."""
        key = client_key(address)
        record = self._records.pop(key, None)
        if record is None:
            record = _Record()
            while len(self._records) >= self.max_addresses:
                self._records.popitem(last=False)  # the one whose last failure is oldest
        self._records[key] = record  # now the most recent
        failures = record.failures
        failures.append(now)
        while failures and failures[0] <= now - self.window:
            failures.popleft()
        if len(failures) > self.limit:
            failures.popleft()  # only the last `limit` matter
        if len(failures) >= self.limit and record.locked_until <= now:
            record.locked_until = now + self.lockout
            failures.clear()  # counted afresh once the lockout ends
            return True
        return False

    def __len__(self) -> int:
        return len(self._records)
