"""Secrets are typed so that their repr is masked: what holds one can be logged whole.

asyncua logs the user of every OPC UA request ("call request (CellUser(...))"), a
traceback's locals and a debug line show reprs, so a repr must never carry a secret.
"""

from __future__ import annotations

from server.opcua.identity import CellUser
from server.security.tokens import Role, TokenStore
from server.settings.model import Settings
from server.settings.webhooks import WebhookTarget

TOKEN = "gc_0123abcd_" + "S" * 43
HOOK = "http://127.0.0.1:9000/hooks/path-secret?auth=query-secret"


def test_an_opcua_users_repr_names_it_without_its_token() -> None:
    user = CellUser(name="plant", token=TOKEN, user_name="plc")
    assert "S" * 43 not in repr(user) and "S" * 43 not in str(user)
    assert "plant" in repr(user) and "plc" in repr(user)
    assert user.token == TOKEN  # still held, for the check at each call


def test_a_stored_tokens_repr_leaves_out_its_hash(tmp_path) -> None:
    """The hash is the key a signed MQTT command is checked with: as secret as the token."""
    entry, token = TokenStore(tmp_path).create("plant", Role.OPERATOR)
    assert entry.secret_sha256 not in repr(entry)
    assert token not in repr(entry) and "plant" in repr(entry)


def test_a_webhooks_repr_shows_its_url_as_shown_everywhere() -> None:
    target = WebhookTarget(url=HOOK, secret="k" * 20)
    for text in (repr(target), str(target)):
        assert "path-secret" not in text and "query-secret" not in text
        assert "http://127.0.0.1:9000/..." in text
        assert "k" * 20 not in text
    assert target.url == HOOK  # posted to as configured


def test_the_settings_repr_holds_no_secret() -> None:
    settings = Settings(
        webhooks=[{"url": HOOK, "secret": "k" * 20}],
        webhook_allowed_networks=["127.0.0.0/8"],  # the destination policy refuses loopback
        mqtt_url="mqtt://127.0.0.1:1883",
        mqtt_password="broker-password",
    )
    for text in (repr(settings), str(settings)):
        for secret in ("path-secret", "query-secret", "k" * 20, "broker-password"):
            assert secret not in text
