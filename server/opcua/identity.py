"""Who an OPC UA session is: an API token as its password, resolved by the HTTP token store.

A session signs in with a user name (free: the token's name reads best in a
client's log) and an API token as its password; the token is checked by the
same `TokenStore` as a bearer token, so its role, its revocation and its name
in the audit trail are the HTTP ones. A wrong or revoked token is refused when
the session is activated (BadUserAccessDenied), as HTTP answers 401. An
anonymous session may browse, read and subscribe; a call from it is refused by
the method itself (server/opcua/methods.py), so the refusal is audited.

The token is checked again at every call, so a revocation takes effect at the
session's next call as at a client's next HTTP request.

asyncua hands a method callback neither the session nor its user: the
permission ruleset, which asyncua asks before each request of a session with
that session's user, leaves the user in a context variable the callback reads
in the same task (asyncua handles one connection's requests in one task, one
after the other).
"""

from __future__ import annotations

from contextvars import ContextVar
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from asyncua import ua
from asyncua.crypto.permission_rules import USER_TYPES, SimpleRoleRuleset, User, UserRole

from server.security.tokens import Principal, TokenStore

if TYPE_CHECKING:
    from asyncua.server.internal_server import InternalServer

ANONYMOUS = "anonymous"
# Everything a session may ask: read, browse, subscribe, call. Never the address space's
# own changes (AddNodes, DeleteNodes, ...): nobody is given asyncua's Admin role.
_SESSION_REQUESTS = frozenset(ua.NodeId(ua.Int32(type_id)) for type_id in USER_TYPES)


@dataclass
class CellUser(User):
    """asyncua's user with the token it signed in with (kept in memory only).

    The token is left out of the repr: asyncua logs the user of every request
    ("call request (CellUser(...))"), and that line must not carry the secret.
    """

    token: str | None = field(default=None, repr=False)
    user_name: str | None = None

    def principal(self, tokens: TokenStore) -> Principal | None:
        """The token's principal now (None: anonymous, or the token was revoked since)."""
        return tokens.verify(self.token) if self.token else None


caller: ContextVar[CellUser | None] = ContextVar("opcua_caller", default=None)


class TokenUsers:
    """asyncua's user manager: anonymous, or a user name with an API token as password."""

    def __init__(self, tokens: TokenStore) -> None:
        self.tokens = tokens

    def get_user(
        self,
        iserver: InternalServer,
        username: str | None = None,
        password: str | None = None,
        certificate: Any = None,
    ) -> User | None:
        if username is None and password is None:
            return CellUser(role=UserRole.User, name=ANONYMOUS)
        principal = self.tokens.verify(password or "")
        if principal is None:
            return None  # BadUserAccessDenied: as HTTP's 401, nothing more said
        return CellUser(role=UserRole.User, name=principal.name, token=password, user_name=username)


class CallerRuleset(SimpleRoleRuleset):
    """Lets a session's requests through (writes fail on read-only nodes) and leaves its
    user for the method callbacks of this request (see the module docstring)."""

    def check_validity(self, user: User, action_type_id: ua.NodeId, body: Any) -> bool:
        caller.set(user if isinstance(user, CellUser) else None)
        return action_type_id in _SESSION_REQUESTS
