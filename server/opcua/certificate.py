"""The OPC UA server's own certificate: self-signed, made once in the data directory, kept.

Why kept: a client trusts a server by its certificate (it is copied into the
client's trust list once); a new certificate at every start would make every
client refuse the server again. The key is 0600 like every secret of the data
directory (server/storage/permissions.py); the certificate is public (DER, as
OPC UA clients import it). Delete both files to have new ones made at the next
start (clients must then trust the new certificate).
"""

from __future__ import annotations

import logging
import socket
from pathlib import Path

from asyncua.crypto import cert_gen
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID

from server.storage.files import write_bytes_atomic
from server.storage.permissions import private_directory

log = logging.getLogger(__name__)

DIRECTORY = "opcua"
CERTIFICATE = "server-certificate.der"
KEY = "server-key.pem"
VALID_DAYS = 3650


def application_uri(cell_id: str) -> str:
    """The server's application URI, also in its certificate (clients compare the two)."""
    return f"urn:glue-cell:{cell_id}"


def ensure_certificate(data_path: Path, cell_id: str) -> tuple[Path, Path]:
    """The certificate and key files, made on first start (blocking: call off the loop)."""
    directory = private_directory(data_path / DIRECTORY)
    certificate, key = directory / CERTIFICATE, directory / KEY
    if certificate.exists() and key.exists():
        return certificate, key
    host = socket.gethostname()
    private_key = cert_gen.generate_private_key()
    names = [x509.UniformResourceIdentifier(application_uri(cell_id)), x509.DNSName(host)]
    made = cert_gen.generate_self_signed_app_certificate(
        private_key,
        f"glue cell {cell_id}",
        {"organizationName": "glue cell"},
        names,
        extended=[ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
        days=VALID_DAYS,
    )
    write_bytes_atomic(key, cert_gen.dump_private_key_as_pem(private_key))  # 0600 (mkstemp)
    write_bytes_atomic(certificate, made.public_bytes(Encoding.DER))
    log.warning(
        "made the OPC UA server certificate %s: a client trusts the server by adding it to "
        "its trust list (docs/plant-integration.md)",
        certificate,
    )
    return certificate, key
