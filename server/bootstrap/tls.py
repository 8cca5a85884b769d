"""https and wss on the HTTP port: the server's certificate and key, checked at start.

Why the server serves TLS itself: with the HMI published on the plant network,
plain http would carry every bearer token and WebSocket ticket across it in clear. A TLS
proxy in front is the other way (docs/security.md, "TLS"); this one needs no
second program on an industrial PC.

uvicorn reads the files when it starts listening, and a key it cannot read there
is a traceback, an encrypted key a prompt on a terminal nobody watches. So the
files are read here first, and each problem is one line naming the setting.
TLS 1.0 and 1.1 are never served: Python's server contexts refuse them by default
since 3.10 (`OP_NO_TLSv1`, `OP_NO_TLSv1_1`; this package needs 3.11), and
tests/e2e/test_tls.py holds the served port to it.
"""

from __future__ import annotations

import ipaddress
import ssl
from pathlib import Path
from typing import Any

from server.common.errors import ConfigurationError
from server.settings.http import HttpSettings

DOCS = 'docs/security.md, "TLS"'


def enabled(settings: HttpSettings) -> bool:
    """Whether the HTTP port serves https (both files set: the settings refuse one alone)."""
    return settings.tls_cert_file is not None and settings.tls_key_file is not None


def _read(name: str, path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise ConfigurationError(f"{name} {path} cannot be read: {exc.strerror or exc}") from None


def check_files(settings: HttpSettings) -> None:
    """ConfigurationError, one line naming the setting, unless the files can serve https.

    Each is read as the server's user; the certificate must be PEM, the key PEM and not
    encrypted (there is nobody to type its password), and the key the certificate's.
    The key's bytes are never part of a message.
    """
    if settings.tls_cert_file is None or settings.tls_key_file is None:
        return
    # Loaded only to check files that are set: cryptography's x509 costs a plain-http
    # server 8 MB and a tenth of a second at start for nothing.
    from cryptography import x509
    from cryptography.exceptions import UnsupportedAlgorithm
    from cryptography.hazmat.primitives import serialization

    cert_file, key_file = settings.tls_cert_file, settings.tls_key_file
    try:
        x509.load_pem_x509_certificates(_read("tls_cert_file", cert_file))
    except ValueError:
        raise ConfigurationError(
            f"tls_cert_file {cert_file} holds no PEM certificate (-----BEGIN CERTIFICATE-----)"
        ) from None
    try:
        serialization.load_pem_private_key(_read("tls_key_file", key_file), password=None)
    except TypeError:  # encrypted
        raise ConfigurationError(
            f"tls_key_file {key_file} is encrypted; give the key without a password "
            "(protect it by its file mode, 0600)"
        ) from None
    except (ValueError, UnsupportedAlgorithm) as exc:  # not PEM, not a key, or not one we take
        raise ConfigurationError(
            f"tls_key_file {key_file} holds no PEM private key ({type(exc).__name__})"
        ) from None
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    try:
        context.load_cert_chain(cert_file, key_file, password=lambda: b"")
    except ssl.SSLError as exc:
        reason = exc.reason or str(exc)
        if "MISMATCH" in str(reason).upper():
            raise ConfigurationError(
                f"tls_key_file {key_file} is not the key of the certificate in "
                f"tls_cert_file {cert_file}"
            ) from None
        raise ConfigurationError(
            f"tls_cert_file {cert_file} and tls_key_file {key_file} cannot serve TLS: {reason}"
        ) from None


def uvicorn_options(settings: HttpSettings) -> dict[str, Any]:
    """uvicorn's TLS options: none for plain http."""
    if settings.tls_cert_file is None or settings.tls_key_file is None:
        return {}
    return {
        "ssl_certfile": str(settings.tls_cert_file),
        "ssl_keyfile": str(settings.tls_key_file),
        "ssl_version": ssl.PROTOCOL_TLS_SERVER,  # TLS 1.2 and 1.3 (see the module's note)
    }


def plain_http_warning(host: str, settings: HttpSettings) -> str | None:
    """The start-up warning for plain http bound beyond loopback, or None.

    Why only a warning: behind a TLS proxy on the same network segment, or on a lab's
    bench, plain http is a choice; what must not happen is making it unknowingly.
    """
    if enabled(settings):
        return None
    try:
        if ipaddress.ip_address(host).is_loopback:
            return None
    except ValueError:  # a host name
        if host == "localhost":
            return None
    return (
        f"serving plain http on {host}: bearer tokens and WebSocket tickets cross the "
        f"network in clear; set tls_cert_file and tls_key_file, or put a TLS proxy in "
        f"front ({DOCS})"
    )
