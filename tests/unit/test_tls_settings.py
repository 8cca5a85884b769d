"""The TLS settings come in pairs, and plain http beyond loopback is said out loud."""

from __future__ import annotations

from pathlib import Path

import pytest

from server.bootstrap import tls
from server.settings.load import SettingsRefused, load_settings
from server.settings.model import Settings

CERT = Path("/etc/glue-cell/tls/cell.pem")
KEY = Path("/etc/glue-cell/tls/cell.key")


def test_a_certificate_without_its_key_is_refused_at_load_naming_what_is_missing() -> None:
    for given, missing in (
        ({"tls_cert_file": CERT}, "tls_key_file"),
        ({"tls_key_file": KEY}, "tls_cert_file"),
    ):
        with pytest.raises(SettingsRefused) as refused:
            load_settings(given)
        message = str(refused.value)
        assert "\n" not in message and missing in message, message
        assert message.startswith("invalid settings: tls_cert_file and tls_key_file go together")


def test_both_or_neither_load() -> None:
    assert not tls.enabled(Settings())
    assert tls.uvicorn_options(Settings()) == {}
    both = Settings(tls_cert_file=CERT, tls_key_file=KEY)
    assert tls.enabled(both)
    options = tls.uvicorn_options(both)
    assert options["ssl_certfile"] == str(CERT) and options["ssl_keyfile"] == str(KEY)


@pytest.mark.parametrize("host", ["0.0.0.0", "192.0.2.10", "::", "cell-3.plant"])
def test_plain_http_beyond_loopback_is_a_warning_pointing_at_the_docs(host: str) -> None:
    warning = tls.plain_http_warning(host, Settings())
    assert warning is not None
    assert host in warning and "in clear" in warning and "docs/security.md" in warning
    assert "\n" not in warning


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.0.2", "::1", "localhost"])
def test_loopback_needs_no_warning(host: str) -> None:
    assert tls.plain_http_warning(host, Settings()) is None


def test_tls_needs_no_warning_anywhere() -> None:
    served = Settings(tls_cert_file=CERT, tls_key_file=KEY)
    assert tls.plain_http_warning("0.0.0.0", served) is None
