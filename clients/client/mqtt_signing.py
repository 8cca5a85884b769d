"""Signing an MQTT command: proof that the sender holds a token, without the token.

A command on `<prefix>/<cell_id>/command/<name>` is published as

    {"token_id": "<8 hex>", "ts_ms": <unix ms>, "nonce": "<16..64 url-safe>",
     "body": {...}, "sig": "<hex HMAC-SHA256>"}

The key is the UTF-8 bytes of the hex SHA-256 digest of the whole token string
(`gc_<id>_<secret>`): what the cell's token store keeps, so the cell checks the
signature without ever having stored the secret, and the secret never crosses
the broker. The signed message is `topic \\n ts_ms \\n nonce \\n canonical(body)`:
the topic binds the command and the cell (a signed `pause` for cell-1 is not a
`start`, nor a `pause` for cell-2), the time and the nonce let the cell refuse
a message replayed later or again (docs/plant-integration.md, "Commands").

Scripts call `sign_command` (or the clients built on it: `gluectl --mqtt`,
`clients.client.mqtt_commands`); nobody should hand-build a signature.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import re
import secrets
import time
from typing import Any

TOKEN_PATTERN = re.compile(r"^gc_([0-9a-f]{8})_[A-Za-z0-9_-]+$")
NONCE_PATTERN = re.compile(r"^[A-Za-z0-9_-]{16,64}$")


def canonical(body: dict[str, Any] | None) -> str:
    """The body as signed: sorted keys, no spaces, ASCII only (`{}` when absent)."""
    return json.dumps(
        {} if body is None else body, sort_keys=True, separators=(",", ":"), ensure_ascii=True
    )


def signing_key(token: str) -> bytes:
    """The HMAC key of a token: its hex SHA-256 digest, as the cell stores it."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest().encode("utf-8")


def signed_text(topic: str, ts_ms: int, nonce: str, body: dict[str, Any] | None) -> bytes:
    """The bytes the signature covers."""
    return f"{topic}\n{ts_ms}\n{nonce}\n{canonical(body)}".encode()


def signature(key: bytes, topic: str, ts_ms: int, nonce: str, body: dict[str, Any] | None) -> str:
    """Hex HMAC-SHA256 of the signed text under `key`."""
    return hmac.new(key, signed_text(topic, ts_ms, nonce, body), hashlib.sha256).hexdigest()


def sign_command(
    token: str,
    topic: str,
    body: dict[str, Any] | None,
    *,
    now_ms: int | None = None,
    nonce: str | None = None,
) -> dict[str, Any]:
    """The message to publish on `topic` for `token`: everything but the token's secret.

    ValueError for something that is not an API token (`gc_<8 hex>_<secret>`), so a
    typo is caught here rather than as a refusal from the cell.
    """
    match = TOKEN_PATTERN.match(token)
    if match is None:
        raise ValueError("not an API token (expected gc_<id>_<secret>)")
    ts_ms = int(time.time() * 1000) if now_ms is None else now_ms
    nonce = secrets.token_urlsafe(18) if nonce is None else nonce
    if not NONCE_PATTERN.match(nonce):
        raise ValueError("a nonce is 16 to 64 url-safe characters")
    body = {} if body is None else body
    return {
        "token_id": match.group(1),
        "ts_ms": ts_ms,
        "nonce": nonce,
        "body": body,
        "sig": signature(signing_key(token), topic, ts_ms, nonce, body),
    }
