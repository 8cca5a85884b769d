"""The signature of a delivery: HMAC-SHA256 over the timestamp and the raw body.

Why the timestamp is signed with the body: a receiver that checks the signature
alone would accept a recorded delivery replayed a day later; with the time under
the signature, it can refuse one whose time is too far from its own clock (five
minutes is usual), and dedupe the rest by the delivery id. Each attempt is signed
with its own time, so a retry an hour later is still fresh.

The signed bytes are `<timestamp>.<body>` (the timestamp in whole seconds, ASCII),
the scheme most receivers already know. docs/plant-integration.md has a receiver.
"""

from __future__ import annotations

import hashlib
import hmac

SIGNATURE_HEADER = "X-Glue-Signature"  # "sha256=<hex>"
TIMESTAMP_HEADER = "X-Glue-Timestamp"  # Unix seconds, as signed
DELIVERY_HEADER = "X-Glue-Delivery"  # the notice's id: the same on every attempt
KIND_HEADER = "X-Glue-Event"  # fault, alert, state, run_completed, part or report


def signature(secret: str, timestamp: int, body: bytes) -> str:
    """The X-Glue-Signature value of `body` sent at `timestamp`."""
    mac = hmac.new(secret.encode(), f"{timestamp}.".encode() + body, hashlib.sha256)
    return f"sha256={mac.hexdigest()}"


def headers(
    secret: str, timestamp: int, body: bytes, delivery_id: str, kind: str
) -> dict[str, str]:
    """Every header of one attempt."""
    return {
        "Content-Type": "application/json",
        TIMESTAMP_HEADER: str(timestamp),
        SIGNATURE_HEADER: signature(secret, timestamp, body),
        DELIVERY_HEADER: delivery_id,
        KIND_HEADER: kind,
    }
