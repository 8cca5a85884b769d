"""What an OPC UA session may send before the cell reads it: a password nobody else
could read, and a method call of a bounded size.

A session's password is an API token, which is also a bearer token for HTTP. Sent in
plain text (UserNameIdentityToken with EncryptionAlgorithm None) on a SecurityPolicy
None channel, or on a Sign channel (signed, not encrypted), anyone on the network
reads it. The endpoints ask for it encrypted with the server's certificate, except in
a SignAndEncrypt channel, and asyncua's Client does so; a hand-made client may not.
asyncua itself accepts the plain form on every channel, so `PasswordGuard` refuses it
before asyncua decodes the token: BadIdentityTokenRejected, a warning in the log and a
row in the audit trail naming whose token it was (so an admin knows what to revoke),
never the token itself.

asyncua tells its user manager neither how the password came nor over what channel.
The guard wraps the one step that reads the token (`InternalServer.decrypt_user_token`,
given the session and the token with its EncryptionAlgorithm) and finds the session's
channel among the connections asyncua keeps (`BinaryServer.clients`, each with its
processor, its session and its secure connection's policy). What it cannot find is
treated as unprotected: then only an encrypted password is accepted.

`CallGuard` bounds a Call request's size before asyncua decodes it (and logs it, at
INFO, arguments and all): a method's inputs are a part id at most, so a request over
`CALL_MAX_BYTES` is refused with BadRequestTooLarge, OPC UA's 413, and audited. A 5 MB
argument then costs neither a decode nor megabytes of log and journal.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any, Final

from asyncua import Server, ua
from asyncua.common.utils import ServiceError

from server.bootstrap.cell import Cell
from server.opcua.identity import ANONYMOUS, CallerRuleset, CellUser
from server.opcua.methods import peer_of
from server.security.tokens import TokenStore
from server.storage.journal import records

log = logging.getLogger(__name__)

ACTIVATE: Final = "OPC UA ActivateSession"
CALL: Final = "OPC UA Call"
# A Call request carries its methods' ids and input arguments: the cell's methods take
# one part id (at most 64 characters) at most, so 64 KiB is far more than any needs.
CALL_MAX_BYTES: Final = 64 * 1024
_CALL_REQUEST: Final = ua.NodeId(ua.Int32(ua.ObjectIds.CallRequest_Encoding_DefaultBinary))
_PROTECTED: Final = frozenset({ua.MessageSecurityMode.SignAndEncrypt})


def _audit(cell: Cell, who: str, address: str, action: str, code: int, detail: str) -> None:
    """A refusal before the cell saw anything: audited as the HTTP gate's refusals are."""
    journal = cell.journal
    if journal is not None:
        outcome = f"refused ({ua.StatusCode(ua.UInt32(code)).name})"
        journal.append(
            [records.audit(time.time(), who, address, action, outcome, detail)], durable=False
        )


def _host(name: object) -> str:
    """The client's address from asyncua's session name, its peer (host, port)."""
    return str(name[0]) if isinstance(name, tuple) and name else "unknown"


def channel_mode(server: Server, session: Any) -> ua.MessageSecurityMode | None:
    """The security mode of the channel `session` speaks on (None: not found).

    When more than one connection holds the session (a client reconnecting), the
    weakest counts.
    """
    binary = server.bserver
    modes = []
    for protocol in list(binary.clients if binary is not None else ()):
        processor = protocol.processor
        if processor is None or processor.session is not session:
            continue
        policy = getattr(getattr(processor, "_connection", None), "security_policy", None)
        modes.append(getattr(policy, "Mode", None))
    weak = [mode for mode in modes if mode not in _PROTECTED]
    if weak or not modes:
        return weak[0] if weak else None
    return ua.MessageSecurityMode.SignAndEncrypt


class PasswordGuard:
    """Refuses a password sent in plain text where the channel does not encrypt it."""

    def __init__(self, server: Server, cell: Cell, tokens: TokenStore) -> None:
        self.server = server
        self.cell = cell
        self.tokens = tokens

    def install(self) -> None:
        """Wrap asyncua's reading of a session's user token (after `Server.init`)."""
        iserver = self.server.iserver
        decrypt: Callable[[Any, ua.UserNameIdentityToken], tuple[str, str]] = (
            iserver.decrypt_user_token
        )

        def guarded(isession: Any, token: ua.UserNameIdentityToken) -> tuple[str, str]:
            if not token.EncryptionAlgorithm:
                mode = channel_mode(self.server, isession)
                if mode not in _PROTECTED:
                    self.refuse(isession, token, mode)
            return decrypt(isession, token)

        setattr(iserver, "decrypt_user_token", guarded)  # noqa: B010 (an instance's method)

    def refuse(
        self,
        isession: Any,
        token: ua.UserNameIdentityToken,
        mode: ua.MessageSecurityMode | None,
    ) -> None:
        """Audit and log the refusal without the password, then raise it for asyncua."""
        raw = token.Password
        secret = raw.decode("utf-8", "replace") if isinstance(raw, bytes) else str(raw or "")
        principal = self.tokens.verify(secret) if secret else None
        names: dict[ua.MessageSecurityMode | None, str] = {
            ua.MessageSecurityMode.None_: "SecurityPolicy None",
            ua.MessageSecurityMode.Sign: "Sign (not encrypted)",
        }
        channel = names.get(mode, "unidentified")
        detail = (
            f"a password sent in plain text on a {channel} channel is refused: encrypt it with "
            "the server's certificate (asyncua and most clients do) or use SignAndEncrypt"
        )
        if principal is not None:
            detail += f"; the token of {principal.name} crossed the network readable: revoke it"
        who = principal.describe() if principal is not None else ANONYMOUS
        address = _host(isession.name)
        _audit(self.cell, who, address, ACTIVATE, ua.StatusCodes.BadIdentityTokenRejected, detail)
        log.warning("%s from %s refused: %s", ACTIVATE, address, detail)
        raise ServiceError(ua.StatusCodes.BadIdentityTokenRejected)


class CallGuard(CallerRuleset):
    """The caller's ruleset (server/opcua/identity.py), refusing an oversized Call first."""

    def __init__(self, server: Server, cell: Cell, tokens: TokenStore) -> None:
        super().__init__()
        self.server = server
        self.cell = cell
        self.tokens = tokens

    def check_validity(self, user: Any, action_type_id: ua.NodeId, body: Any) -> bool:
        if action_type_id == _CALL_REQUEST and len(body) > CALL_MAX_BYTES:
            self._refuse(user, len(body))
        return super().check_validity(user, action_type_id, body)

    def _refuse(self, user: Any, size: int) -> None:
        cell_user = user if isinstance(user, CellUser) else None
        principal = cell_user.principal(self.tokens) if cell_user is not None else None
        who = principal.describe() if principal is not None else ANONYMOUS
        address = peer_of(self.server, cell_user)
        detail = (
            f"the call request is {size} bytes; at most {CALL_MAX_BYTES} are read "
            "(a method's inputs are a part id at most)"
        )
        _audit(self.cell, who, address, CALL, ua.StatusCodes.BadRequestTooLarge, detail)
        log.info("%s from %s refused: %s", CALL, address, detail)
        raise ServiceError(ua.StatusCodes.BadRequestTooLarge)
