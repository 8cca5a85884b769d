"""A hand-edited tokens.json is refused at load, naming the entry and the field.

Loaded unchecked, a role that is not a role would make every request with that
token a 500, /estop included. The store reads each entry strictly, once, at
start-up, and a bad one stops the server before it serves anything.
"""

from __future__ import annotations

import json
from typing import Any

import pytest

from server.common.errors import ConfigurationError
from server.security.tokens import Role, TokenStore

GOOD: dict[str, Any] = {
    "id": "0a1b2c3d",
    "name": "line 2 HMI",
    "role": "operator",
    "secret_sha256": "0" * 64,
    "created_at": 1_700_000_000.0,
    "revoked_at": None,
}


def _write(tmp_path, document: Any) -> None:
    (tmp_path / "tokens.json").write_text(json.dumps(document), encoding="utf-8")


def _refusal(tmp_path, document: Any) -> str:
    _write(tmp_path, document)
    with pytest.raises(ConfigurationError) as refused:
        TokenStore(tmp_path)
    message = str(refused.value)
    assert "\n" not in message and "tokens.json" in message
    return message


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        ({"role": "superuser"}, "entry '0a1b2c3d': role: 'superuser' is not a role"),
        ({"role": 3}, "entry '0a1b2c3d': role: "),
        ({"created_at": "yesterday"}, "entry '0a1b2c3d': created_at: "),
        ({"created_at": True}, "entry '0a1b2c3d': created_at: "),
        ({"revoked_at": "never"}, "entry '0a1b2c3d': revoked_at: "),
        ({"name": ""}, "entry '0a1b2c3d': name: "),
        ({"secret_sha256": "abc"}, "entry '0a1b2c3d': secret_sha256: "),
        ({"expires": 5}, "entry '0a1b2c3d': expires: "),
        ({"id": "admin"}, "entry 'admin': id: "),
    ],
)
def test_a_bad_field_names_the_entry_and_the_field(tmp_path, change, expected) -> None:
    assert expected in _refusal(tmp_path, {"tokens": [{**GOOD, **change}]})


def test_a_missing_field_is_named(tmp_path) -> None:
    entry = {k: v for k, v in GOOD.items() if k != "secret_sha256"}
    assert "entry '0a1b2c3d': secret_sha256: " in _refusal(tmp_path, {"tokens": [entry]})


def test_an_entry_without_a_usable_id_is_named_by_its_place(tmp_path) -> None:
    second = {k: v for k, v in GOOD.items() if k != "id"}
    message = _refusal(tmp_path, {"tokens": [GOOD, second]})
    assert "entry 2 (no id): id: " in message
    assert "entry 2 (not an object)" in _refusal(tmp_path, {"tokens": [GOOD, "gc_x"]})


def test_a_duplicate_id_is_refused(tmp_path) -> None:
    message = _refusal(tmp_path, {"tokens": [GOOD, {**GOOD, "name": "copy"}]})
    assert "entry '0a1b2c3d'" in message and "more than once" in message


@pytest.mark.parametrize("document", [[], {"tokens": {}}, {"tokens": [], "extra": 1}, 5])
def test_a_document_of_the_wrong_shape_is_refused(tmp_path, document) -> None:
    _refusal(tmp_path, document)


def test_good_entries_load(tmp_path) -> None:
    revoked = {**GOOD, "id": "ffffffff", "role": "admin", "revoked_at": 1_700_000_100}
    _write(tmp_path, {"tokens": [GOOD, revoked]})
    entries = {e["id"]: e for e in TokenStore(tmp_path).list()}
    assert entries["0a1b2c3d"]["role"] == "operator" and entries["ffffffff"]["revoked_at"]
    assert Role.parse(entries["ffffffff"]["role"]) is Role.ADMIN
