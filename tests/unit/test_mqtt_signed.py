"""The signed MQTT command, pure: what the client signs, the cell accepts once, fresh.

clients/client/mqtt_signing.py signs; server/mqtt/signed.py verifies with the key the
token store keeps (the token's hex SHA-256). Each refusal is a status and a detail
that never repeats the token."""

from __future__ import annotations

import hashlib

import pytest

from clients.client.mqtt_signing import canonical, sign_command
from server.mqtt.signed import NonceCache, Refusal, Verified, verify
from server.security.tokens import Principal, Role

TOKEN = "gc_0123abcd_" + "s" * 43
TOPIC = "glue/cell-1/command/start"
NOW = 1_800_000_000_000
PRINCIPAL = Principal("0123abcd", "line 3", Role.OPERATOR)


def keys(token_id: str) -> tuple[bytes, Principal] | None:
    if token_id != "0123abcd":
        return None
    return hashlib.sha256(TOKEN.encode()).hexdigest().encode(), PRINCIPAL


def check(message: object, *, nonces: NonceCache | None = None, now: int = NOW, topic=TOPIC):
    return verify(
        message,
        topic,
        now_ms=now,
        keys=keys,
        nonces=nonces if nonces is not None else NonceCache(),
        max_age_ms=30_000,
        max_skew_ms=5_000,
    )


def test_a_signed_command_is_accepted_once_and_carries_no_secret() -> None:
    body = {"workpiece_id": "demo", "contour_matching": False}
    message = sign_command(TOKEN, TOPIC, body, now_ms=NOW)
    assert set(message) == {"token_id", "ts_ms", "nonce", "body", "sig"}
    assert TOKEN.split("_")[2] not in str(message)  # the secret never goes on the wire
    nonces = NonceCache()
    assert check(message, nonces=nonces) == Verified(PRINCIPAL, body, NOW)
    again = check(message, nonces=nonces, now=NOW + 1000)
    assert isinstance(again, Refusal) and "replayed" in again.detail


def test_the_canonical_body_is_sorted_compact_ascii() -> None:
    assert canonical({"b": 1, "a": "é"}) == '{"a":"\\u00e9","b":1}'
    assert canonical(None) == "{}"


@pytest.mark.parametrize(
    ("age_ms", "word"),
    [(30_001, "stale"), (-5_001, "future")],
)
def test_stale_and_future_messages_are_refused(age_ms: int, word: str) -> None:
    message = sign_command(TOKEN, TOPIC, None, now_ms=NOW - age_ms)
    refused = check(message)
    assert isinstance(refused, Refusal) and refused.status == 401 and word in refused.detail


def test_the_edges_of_the_window_are_accepted() -> None:
    for ts in (NOW - 30_000, NOW + 5_000):
        assert isinstance(check(sign_command(TOKEN, TOPIC, None, now_ms=ts)), Verified)


@pytest.mark.parametrize(
    "change",
    [
        {"body": {"workpiece_id": "other"}},
        {"ts_ms": NOW + 1},
        {"nonce": "n" * 24},
        {"sig": "0" * 64},
    ],
)
def test_any_change_breaks_the_signature(change: dict) -> None:
    message = {**sign_command(TOKEN, TOPIC, {"workpiece_id": "demo"}, now_ms=NOW), **change}
    refused = check(message)
    assert isinstance(refused, Refusal) and "signature" in refused.detail


def test_a_signature_for_another_topic_is_refused() -> None:
    message = sign_command(TOKEN, "glue/cell-2/command/start", None, now_ms=NOW)
    assert isinstance(check(message), Refusal)  # not for this cell
    message = sign_command(TOKEN, "glue/cell-1/command/pause", None, now_ms=NOW)
    assert isinstance(check(message), Refusal)  # nor this command


def test_unknown_ids_malformed_fields_and_the_old_form_are_refused() -> None:
    other = "gc_ffffffff_" + "s" * 43
    assert check(sign_command(other, TOPIC, None, now_ms=NOW)) == Refusal(
        401, "the token is unknown or revoked"
    )
    old = check({"token": TOKEN, "body": {}})
    assert isinstance(old, Refusal) and old.status == 401 and "sign" in old.detail
    assert TOKEN not in old.detail
    good = sign_command(TOKEN, TOPIC, None, now_ms=NOW)
    for field, bad in [
        ("token_id", "XYZ"),
        ("ts_ms", "1"),
        ("ts_ms", True),
        ("nonce", "short"),
        ("sig", "zz"),
    ]:
        refused = check({**good, field: bad})
        assert isinstance(refused, Refusal) and refused.detail.startswith(field), field
    assert isinstance(check([1, 2]), Refusal)


def test_the_nonce_cache_is_bounded_and_refuses_what_it_can_no_longer_check() -> None:
    nonces = NonceCache(capacity=3)
    sent = [sign_command(TOKEN, TOPIC, None, now_ms=NOW + i) for i in range(5)]
    for message in sent:
        assert isinstance(check(message, nonces=nonces, now=NOW + 10), Verified)
    assert len(nonces) == 3
    # The first two nonces were dropped: their messages are refused by their time.
    for message in sent[:2]:
        refused = check(message, nonces=nonces, now=NOW + 10)
        assert isinstance(refused, Refusal) and "stale" in refused.detail
    # And a nonce is forgotten once its message is past the window.
    later = sign_command(TOKEN, TOPIC, None, now_ms=NOW + 40_000)
    assert isinstance(check(later, nonces=nonces, now=NOW + 40_000), Verified)
    assert len(nonces) == 1


def test_a_bad_signature_does_not_use_up_the_nonce() -> None:
    nonces = NonceCache()
    good = sign_command(TOKEN, TOPIC, None, now_ms=NOW)
    assert isinstance(check({**good, "sig": "0" * 64}, nonces=nonces), Refusal)
    assert isinstance(check(good, nonces=nonces), Verified)


def test_a_script_mistake_is_caught_when_signing() -> None:
    with pytest.raises(ValueError, match="not an API token"):
        sign_command("hunter2", TOPIC, None)
    with pytest.raises(ValueError, match="nonce"):
        sign_command(TOKEN, TOPIC, None, nonce="x")


def test_the_token_store_gives_the_key_the_client_signs_with(tmp_path) -> None:
    """The client's key (the token's hex SHA-256) is what the store keeps; revoked: none."""
    from server.security.tokens import TokenStore

    store = TokenStore(tmp_path)
    entry, token = store.create("mes", Role.OPERATOR)
    message = sign_command(token, TOPIC, {"workpiece_id": "demo"}, now_ms=NOW)
    checked = verify(
        message,
        TOPIC,
        now_ms=NOW,
        keys=store.mqtt_key,
        nonces=NonceCache(),
        max_age_ms=30_000,
        max_skew_ms=5_000,
    )
    assert isinstance(checked, Verified) and checked.principal.token_id == entry.id
    store.revoke(entry.id)
    assert store.mqtt_key(entry.id) is None
    assert store.mqtt_key("ffffffff") is None
