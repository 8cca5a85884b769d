"""API tokens: bearer secrets for people and programs, each with one role.

A token reads `gc_<id>_<secret>`. Only a SHA-256 of the secret is stored
(`<data>/tokens.json`, written atomically, mode 0600); the id finds the entry,
the hash is compared in constant time. The secrets are 32 random bytes, so a
plain hash is enough: there is nothing to brute-force. Revocation takes effect
on the next request.

On first start, with no token at all, an admin token is created and written to
`<data>/admin.token` (mode 0600) for the CLI and the dashboard's login; the log
says where it is, never what it is.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import os
import re
import secrets
import threading
import time
from dataclasses import asdict, dataclass, field, replace
from enum import IntEnum
from pathlib import Path
from typing import Any

from server.common.errors import ConfigurationError
from server.security.token_file import read_entries
from server.storage.files import write_bytes_atomic

log = logging.getLogger(__name__)
TOKEN_PATTERN = re.compile(r"^gc_([0-9a-f]{8})_([A-Za-z0-9_-]{20,100})$")


class Role(IntEnum):
    """Each role may do everything the roles below it may."""

    VIEWER = 1  # state, history, KPIs, /ws
    OPERATOR = 2  # start, pause, resume, cancel, create workpiece
    MAINTENANCE = 3  # calibrations, reset, workpiece library edits
    ADMIN = 4  # settings, tokens, audit

    @property
    def label(self) -> str:
        return self.name.lower()

    @classmethod
    def parse(cls, name: str) -> Role:
        try:
            return cls[name.upper()]
        except KeyError:
            raise ValueError(
                f"unknown role {name!r}: viewer, operator, maintenance or admin"
            ) from None


@dataclass(frozen=True)
class Principal:
    """Who made a request."""

    token_id: str
    name: str
    role: Role

    def describe(self) -> str:
        return f"{self.name} ({self.role.label}, token {self.token_id})"


@dataclass
class TokenEntry:
    """One stored token. Its `secret_sha256` is out of the repr: it is the key a signed
    MQTT command is checked with, so it is as secret as the token (docs/security.md)."""

    id: str
    name: str
    role: str
    secret_sha256: str = field(repr=False)
    created_at: float
    revoked_at: float | None = None

    def public(self) -> dict[str, Any]:
        """The entry without its hash: what an admin may list."""
        return {k: v for k, v in asdict(self).items() if k != "secret_sha256"}


class LastAdminToken(ValueError):
    """Revoking this token would leave no admin token: nobody could make or revoke one."""


def last_admin_refusal(entry: TokenEntry) -> str:
    return (
        f"token {entry.id} ({entry.name}) is the last admin token: revoked, it would leave "
        "nobody able to make or revoke tokens. Create another admin token first "
        "(POST /tokens, role admin), then revoke this one"
    )


def _digest(secret: str) -> str:
    return hashlib.sha256(secret.encode("utf-8")).hexdigest()


class TokenStore:
    """The tokens of one data directory."""

    def __init__(self, data_path: Path) -> None:
        self.path = data_path / "tokens.json"
        self.admin_token_path = data_path / "admin.token"
        self._lock = threading.Lock()
        self._entries: dict[str, TokenEntry] = {}
        # Each entry's Principal, built once: every request is verified (GET /state
        # included), and entries are replaced, never changed, so identity says it is current.
        self._principals: dict[str, tuple[TokenEntry, Principal]] = {}
        self._load()

    def _load(self) -> None:
        try:
            document = json.loads(self.path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            return
        except ValueError as exc:
            raise ConfigurationError(
                f"{self.path} is not valid JSON ({exc}); restore it or remove it "
                "to start with a new admin token"
            ) from exc
        roles = [role.label for role in Role]
        entries = read_entries(self.path, document, roles)  # each checked: see token_file.py
        self._entries = {e.id: TokenEntry(**e.model_dump()) for e in entries}

    def _save(self, entries: dict[str, TokenEntry]) -> None:
        """Write `entries` as the file; the caller applies them in memory only afterwards."""
        data = json.dumps({"tokens": [asdict(e) for e in entries.values()]}, indent=2)
        write_bytes_atomic(self.path, data.encode("utf-8"))
        os.chmod(self.path, 0o600)

    def ensure_admin(self) -> Path | None:
        """Create an admin token if no unrevoked one exists; where it was written.

        On first start there is no token at all. Later, a tokens.json whose admin
        tokens are all revoked (edited by hand, or from before revoking the last one
        was refused) would leave nobody able to make or revoke a token: a restart
        recovers, with a new admin token beside the data.
        """
        with self._lock:
            if self._live_admins():
                return None
            first = not self._entries
        name = "initial admin" if first else "recovery admin"
        _, secret = self.create(name, Role.ADMIN)
        write_bytes_atomic(self.admin_token_path, (secret + "\n").encode("utf-8"))
        os.chmod(self.admin_token_path, 0o600)
        why = "no API token existed" if first else "every admin token was revoked"
        log.warning("%s: created an admin token in %s (mode 0600)", why, self.admin_token_path)
        return self.admin_token_path

    def _live_admins(self) -> list[str]:
        """The ids of the unrevoked admin tokens (call with the lock held)."""
        admin = Role.ADMIN.label
        return [e.id for e in self._entries.values() if e.role == admin and e.revoked_at is None]

    def is_last_admin(self, token_id: str) -> bool:
        """Is `token_id` the only unrevoked admin token?"""
        with self._lock:
            return self._live_admins() == [token_id]

    def create(self, name: str, role: Role) -> tuple[TokenEntry, str]:
        """A new token, saved; the secret is returned once and never stored."""
        entry, token = self.mint(name, role)
        self.add(entry)
        return entry, token

    @staticmethod
    def mint(name: str, role: Role) -> tuple[TokenEntry, str]:
        """A new token and its entry, not yet stored (`add` stores it)."""
        token_id = secrets.token_hex(4)
        secret = secrets.token_urlsafe(32)
        token = f"gc_{token_id}_{secret}"
        return TokenEntry(token_id, name, role.label, _digest(token), time.time()), token

    def add(self, entry: TokenEntry) -> None:
        """Store a minted entry: in the file first, then in memory (OSError: neither)."""
        with self._lock:
            entries = {**self._entries, entry.id: entry}
            self._save(entries)
            self._entries = entries

    def get(self, token_id: str) -> TokenEntry:
        """The entry of `token_id`; KeyError for an unknown id."""
        with self._lock:
            return self._entries[token_id]

    def list(self) -> list[dict[str, Any]]:
        with self._lock:
            return [e.public() for e in self._entries.values()]

    def revoke(self, token_id: str) -> TokenEntry:
        """Revoke at once; KeyError for an unknown id.

        The file is written first and memory changed only once it is: a revocation
        that could not be saved (OSError) is not applied, or it would come back at
        the next start.
        """
        with self._lock:
            entry = self._entries[token_id]
            if entry.revoked_at is not None:
                return entry
            if self._live_admins() == [token_id]:
                raise LastAdminToken(last_admin_refusal(entry))
            revoked = replace(entry, revoked_at=time.time())
            entries = {**self._entries, token_id: revoked}
            self._save(entries)
            self._entries = entries
            return revoked

    def mqtt_key(self, token_id: str) -> tuple[bytes, Principal] | None:
        """The signing key of an unrevoked token and its principal, else None.

        An MQTT command is signed with the token's stored digest (the hex SHA-256 of
        the whole token, as bytes): the sender proves it holds the token without the
        secret crossing the broker, and nothing new is stored (server/mqtt/signed.py).
        """
        entry = self._entries.get(token_id)
        if entry is None or entry.revoked_at is not None:
            return None
        cached = self._principals.get(entry.id)
        if cached is not None and cached[0] is entry:
            return entry.secret_sha256.encode("utf-8"), cached[1]
        principal = Principal(entry.id, entry.name, Role.parse(entry.role))
        self._principals[entry.id] = (entry, principal)
        return entry.secret_sha256.encode("utf-8"), principal

    def verify(self, token: str) -> Principal | None:
        """The principal of a valid, unrevoked token, else None."""
        match = TOKEN_PATTERN.match(token)
        if match is None:
            return None
        entry = self._entries.get(match.group(1))
        if entry is None or entry.revoked_at is not None:
            return None
        if not hmac.compare_digest(entry.secret_sha256, _digest(token)):
            return None
        cached = self._principals.get(entry.id)
        if cached is not None and cached[0] is entry:
            return cached[1]
        principal = Principal(entry.id, entry.name, Role.parse(entry.role))
        self._principals[entry.id] = (entry, principal)
        return principal
