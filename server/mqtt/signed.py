"""Checking a signed MQTT command: who sent it, that it is fresh, and that it is new.

Pure (no I/O, the clock handed in): `verify` takes the decoded message, the topic it
came on, the time, a way to find a token's key by its id, and the nonces already
seen; it answers the principal or a refusal with its status and detail.

The wire format (clients/client/mqtt_signing.py signs it):

    {"token_id": "<8 hex>", "ts_ms": <unix ms>, "nonce": "<16..64 url-safe>",
     "body": {...}, "sig": "<hex HMAC-SHA256>"}

keyed with the token's stored digest, over `topic \\n ts_ms \\n nonce \\n canonical(body)`.
Why each check:

- the old `{"token": ...}` form is refused (401, telling the sender to sign): the
  token would have crossed the broker in clear, readable by any subscriber of `#`;
- a message older than `max_age_ms`, or ahead of the cell's clock by more than
  `max_skew_ms`, is refused: a captured message cannot be replayed later;
- a nonce seen within that window is refused: nor replayed at once. The cache only
  needs to cover the window (older messages are refused by their time anyway). It is
  bounded in size too, so a flood of signed messages cannot grow memory: when full,
  the oldest nonce goes, and from then on no message older than it is accepted (its
  nonce could no longer be checked);
- the signature is compared in constant time, after the token is found by its id
  (an unknown or revoked id: 401 with no hint which).

The nonce is recorded only for a message whose signature is good, so nobody without
a token can fill the cache.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import re
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from server.security.tokens import Principal

TOKEN_ID = re.compile(r"^[0-9a-f]{8}$")
NONCE = re.compile(r"^[A-Za-z0-9_-]{16,64}$")
SIGNATURE = re.compile(r"^[0-9a-f]{64}$")
SIGN_HINT = (
    "sign the command: send token_id, ts_ms, nonce, body and sig, never the token "
    "(gluectl --mqtt or clients/client/mqtt_signing.py: sign_command)"
)
DEFAULT_NONCE_CAPACITY = 100_000

KeyLookup = Callable[[str], "tuple[bytes, Principal] | None"]


@dataclass(frozen=True)
class Refusal:
    """Why a message is not a command: the status and detail its answer carries."""

    status: int
    detail: str


@dataclass(frozen=True)
class Verified:
    """A signed, fresh, new command: who sent it, its body, and when it was signed (the
    sender's clock, unix ms)."""

    principal: Principal
    body: Any
    ts_ms: int


class NonceCache:
    """Nonces seen, each with its message's time, oldest first; bounded in size and time."""

    def __init__(self, capacity: int = DEFAULT_NONCE_CAPACITY) -> None:
        self.capacity = capacity
        self._seen: OrderedDict[str, int] = OrderedDict()  # nonce -> ts_ms, in arrival order
        self._floor_ms: int | None = None  # no message older than this: its nonce may be gone

    def __len__(self) -> int:
        return len(self._seen)

    def forget_before(self, oldest_ms: int) -> None:
        """Drop the nonces of messages older than the window (they are refused by age)."""
        # From the first to arrive, while stale: O(1) a message. One that arrived later
        # with an older time stays a little longer, which refuses nothing it should not.
        while self._seen:
            nonce, ts_ms = next(iter(self._seen.items()))
            if ts_ms >= oldest_ms:
                return
            del self._seen[nonce]

    def seen(self, nonce: str) -> bool:
        return nonce in self._seen

    @property
    def floor_ms(self) -> int | None:
        """The oldest message time still accepted because its nonce could be checked."""
        return self._floor_ms

    def add(self, nonce: str, ts_ms: int) -> None:
        self._seen[nonce] = ts_ms
        while len(self._seen) > self.capacity:
            _, dropped_ts = self._seen.popitem(last=False)
            if self._floor_ms is None or dropped_ts >= self._floor_ms:
                self._floor_ms = dropped_ts + 1


def signed_text(topic: str, ts_ms: int, nonce: str, body: Any) -> bytes:
    """What the signature covers (clients/client/mqtt_signing.py: the same)."""
    canonical = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return f"{topic}\n{ts_ms}\n{nonce}\n{canonical}".encode()


def verify(
    message: Any,
    topic: str,
    *,
    now_ms: int,
    keys: KeyLookup,
    nonces: NonceCache,
    max_age_ms: int,
    max_skew_ms: int,
) -> Verified | Refusal:
    """The principal and body of a signed command, or why it is refused."""
    if not isinstance(message, dict):
        return Refusal(400, f"the payload must be a JSON object; {SIGN_HINT}")
    if "token" in message:
        return Refusal(
            401, f"a token in the payload is refused (readable on the broker); {SIGN_HINT}"
        )
    token_id, ts_ms, nonce = message.get("token_id"), message.get("ts_ms"), message.get("nonce")
    sig, body = message.get("sig"), message.get("body", {})
    if not isinstance(token_id, str) or not TOKEN_ID.match(token_id):
        return Refusal(401, f"token_id: missing or not 8 hex digits; {SIGN_HINT}")
    if not isinstance(ts_ms, int) or isinstance(ts_ms, bool):
        return Refusal(401, "ts_ms: missing or not an integer (the sender's unix time in ms)")
    if not isinstance(nonce, str) or not NONCE.match(nonce):
        return Refusal(401, "nonce: missing or not 16 to 64 url-safe characters")
    if not isinstance(sig, str) or not SIGNATURE.match(sig):
        return Refusal(401, "sig: missing or not a hex HMAC-SHA256")
    if body is None:
        body = {}
    found = keys(token_id)
    if found is None:
        return Refusal(401, "the token is unknown or revoked")
    key, principal = found
    expected = hmac.new(key, signed_text(topic, ts_ms, nonce, body), hashlib.sha256).hexdigest()
    if not hmac.compare_digest(expected, sig):
        return Refusal(401, "the signature does not match (wrong token, topic or body)")
    oldest = now_ms - max_age_ms
    if ts_ms < oldest or (nonces.floor_ms is not None and ts_ms < nonces.floor_ms):
        age_s = (now_ms - ts_ms) / 1000
        return Refusal(
            401,
            f"stale: sent {age_s:.1f} s ago, more than {max_age_ms / 1000:g} s "
            "(mqtt_command_max_age); check the sender's clock",
        )
    if ts_ms > now_ms + max_skew_ms:
        ahead_s = (ts_ms - now_ms) / 1000
        return Refusal(
            401,
            f"from the future: {ahead_s:.1f} s ahead of the cell's clock, more than "
            f"{max_skew_ms / 1000:g} s (mqtt_command_max_skew); check the sender's clock",
        )
    nonces.forget_before(oldest)
    if nonces.seen(nonce):
        return Refusal(401, "replayed: this nonce was already used")
    nonces.add(nonce, ts_ms)
    return Verified(principal, body, ts_ms)
