"""What tokens.json must hold, checked entry by entry when the server starts.

Why at load and not at use: the file is edited by hand now and then (a token
renamed, a role changed, a copy from another cell). Loaded unchecked, a role
that is not a role would make every request with that token a 500 when its role
is read, the software stop included. Checked here, a bad entry stops the start
with one line naming the file, the entry (its id, or its place when it has
none) and the field, before the server answers anything.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from server.common.errors import ConfigurationError
from server.common.values import FiniteNumber

TOKEN_ID_PATTERN = r"^[0-9a-f]{8}$"  # the <id> of gc_<id>_<secret>


class StoredToken(BaseModel):
    """One entry of tokens.json, as the store writes it."""

    model_config = ConfigDict(extra="forbid", strict=True)

    id: str = Field(pattern=TOKEN_ID_PATTERN)
    name: str = Field(min_length=1)
    role: str
    secret_sha256: str = Field(pattern=r"^[0-9a-f]{64}$")
    created_at: FiniteNumber = Field(ge=0)
    revoked_at: FiniteNumber | None = Field(None, ge=0)


def _label(index: int, entry: Any) -> str:
    if not isinstance(entry, dict):
        return f"entry {index} (not an object)"
    token_id = entry.get("id")
    return f"entry {token_id!r}" if isinstance(token_id, str) else f"entry {index} (no id)"


def _first_problem(exc: ValidationError) -> str:
    first = exc.errors()[0]
    field = ".".join(str(part) for part in first["loc"]) or "entry"
    message = first["msg"].removeprefix("Value error, ")
    more = exc.error_count() - 1
    return f"{field}: {message}" + (f" (and {more} more)" if more else "")


def read_entries(path: Path, document: Any, roles: Sequence[str]) -> list[StoredToken]:
    """The entries of a parsed tokens.json; ConfigurationError naming the first bad one.

    `roles` are the role names there are (the store's `Role` labels).
    """
    if not (isinstance(document, dict) and set(document) == {"tokens"}):
        raise ConfigurationError(
            f'{path} must hold one object {{"tokens": [...]}}; restore it from a backup, '
            "or remove it to start with a new admin token"
        )
    raw = document["tokens"]
    if not isinstance(raw, list):
        raise ConfigurationError(f'{path}: "tokens" must be a list of entries')
    entries: list[StoredToken] = []
    seen: set[str] = set()
    for index, entry in enumerate(raw, start=1):
        where = f"{path}: {_label(index, entry)}"
        if not isinstance(entry, dict):
            raise ConfigurationError(f"{where}: each entry must be an object")
        try:
            token = StoredToken.model_validate(entry)
        except ValidationError as exc:
            raise ConfigurationError(
                f"{where}: {_first_problem(exc)}; correct the entry or remove it "
                "(a removed token stops working)"
            ) from None
        if token.role not in roles:
            raise ConfigurationError(
                f"{where}: role: {token.role!r} is not a role ({', '.join(roles)}); "
                "correct the entry or remove it (a removed token stops working)"
            )
        if token.id in seen:
            raise ConfigurationError(f"{where}: the id appears more than once; remove a copy")
        seen.add(token.id)
        entries.append(token)
    return entries
