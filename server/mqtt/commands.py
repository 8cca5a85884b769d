"""Commands received over MQTT: the same path, roles, audit and answers as HTTP.

A message on `<prefix>/<cell_id>/command/<name>` is a signed command
(server/mqtt/signed.py: `token_id`, `ts_ms`, `nonce`, `body`, `sig`); `name` is
a command of the catalogue (server/commands/catalogue.py: start, pause, resume,
cancel, reset, estop, home, jog, calibrate-robot, calibrate-camera,
create-workpiece), the HTTP route's word. The token is found by its
id in the HTTP gate's store, the signature proves the sender holds it, the time
and nonce that the message is fresh and new; the role is the one
the catalogue gives the command, which the HTTP gate reads too, so the two doors
cannot drift apart. The body is validated by the command's own model and turned
into the worker's payload by the same function (server/commands/answers.py), and
the command goes to `Cell.command` with an audit note, whose row is committed
with the event. The answer is the HTTP answer's JSON with its status beside it
(`"status": 202` and so on).

What no command reaches the worker with (unsigned, the old `{"token": ...}`
form, a bad signature, an unknown or revoked token id, stale, from the future,
a nonce already used, too low a role, an unknown command, a body that is not
valid) is refused here and written to the audit trail like the HTTP gate's
refusals; no refusal repeats what the message carried. An e-stop goes by the
e-stop path (`Cell.command` → `EmergencyStops.stop`: the devices halted
before the event is queued) and is never refused over its body: it is made,
and the 422 says so, as over HTTP. It is refused, like any command, when it is
not signed, fresh and new: a replayed stop must not stop the cell again.

A command signed no later than a stop of the same token (to the millisecond) is refused
(409) when it is read after that stop: the stop lane's connection brings a stop ahead
of the commands still queued for the other, and nothing sent before a stop is decided
after it (server/core/machine/decide.py, "asked before a stop"); the sender's own
clock orders its own messages.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from typing import Any

from server.bootstrap.cell import Cell
from server.commands.answers import answer_of, audit_label, invalid_request, payload_of
from server.commands.catalogue import is_stop, spec_of
from server.commands.requests import RETRY_AFTER_S
from server.common.errors import EventQueueFull, JournalUnavailable, WorkerStopped
from server.core.machine.decide import ASKED_BEFORE_STOP
from server.core.machine.events import AuditNote, Payload, StopPayload
from server.core.machine.transitions import Command, normalize_command
from server.mqtt.signed import NonceCache, Refusal, verify
from server.security.tokens import Principal, TokenStore
from server.storage.journal import records

log = logging.getLogger(__name__)

Answer = tuple[int, dict[str, Any]]


class CommandDoor:
    """Runs one MQTT command message and says what to answer."""

    def __init__(
        self,
        cell: Cell,
        tokens: TokenStore,
        address: str,
        *,
        max_age_s: float = 30.0,
        max_skew_s: float = 5.0,
        clock: Callable[[], float] = time.time,
        source: str = "mqtt",
    ) -> None:
        self.cell = cell
        self.source = source  # the transport the audit and the event name (mqtt, sparkplug)
        self.tokens = tokens
        self.address = address  # what the audit records as "from where": the broker
        self.max_age_ms = int(max_age_s * 1000)
        self.max_skew_ms = int(max_skew_s * 1000)
        self.nonces = NonceCache()
        # per token id, the latest signed time of a stop it sent (a command signed before it
        # by the same sender is refused, whichever connection brought it first)
        self._stop_signed_ms: dict[str, int] = {}
        self._clock = clock

    async def handle(
        self, topic: str, name: str, raw: bytes, asked_at_estops: int | None = None
    ) -> Answer:
        """Check, run and answer one command message; every refusal is audited.
        `asked_at_estops`: the e-stops counted when it was read off the socket."""
        action = f"MQTT {topic}"
        command = normalize_command(name)
        if command is None:
            return self.refuse(None, action, 404, f"unknown command {name!r}")
        try:
            message = json.loads(raw or b"{}")
        except (ValueError, UnicodeDecodeError):
            return self.refuse(None, action, 400, "the payload is not JSON")
        checked = verify(
            message,
            topic,
            now_ms=int(self._clock() * 1000),
            keys=self.tokens.mqtt_key,
            nonces=self.nonces,
            max_age_ms=self.max_age_ms,
            max_skew_ms=self.max_skew_ms,
        )
        if isinstance(checked, Refusal):
            return self.refuse(None, action, checked.status, checked.detail)
        token = checked.principal.token_id
        if is_stop(command):
            self._stop_signed_ms[token] = max(checked.ts_ms, self._stop_signed_ms.get(token, -1))
        elif checked.ts_ms <= self._stop_signed_ms.get(token, -1):
            # Signed no later than a stop of the same sender (its clock counts milliseconds:
            # within one, the safe side), read only now: the stop lane's connection had the
            # stop first (decide.py, "asked before a stop").
            return self.refuse(checked.principal, action, 409, ASKED_BEFORE_STOP)
        return await self.execute(checked.principal, action, command, checked.body, asked_at_estops)

    async def execute(
        self,
        principal: Principal,
        action: str,
        command: Command,
        body: Any,
        asked_at_estops: int | None = None,
    ) -> Answer:
        """Run a command whose sender is known: the role, the body, then the cell.

        The Sparkplug node comes in here too, with the principal of the token it runs
        commands as (server/mqtt/sparkplug/node.py): the same role check, body model,
        stop rule and audit as a signed message.
        """
        needed = spec_of(command).role
        if principal.role < needed:
            detail = (
                f"this needs the {needed.label} role; {principal.name} has {principal.role.label}"
            )
            return self.refuse(principal, action, 403, detail)
        payload, errors = payload_of(command, body)
        if errors:  # as HTTP's 422: the detail, and each field with its message
            problem = invalid_request(errors)
            if command is Command.ESTOP:  # a stop is never refused over its body
                _, answer = await self._run(principal, action, command, StopPayload(None))
                answer["message"] = f"the stop was made without its reason: {answer['message']}"
                return 422, {"detail": problem, "errors": errors, **answer}
            status, body = self.refuse(principal, action, 422, problem)
            return status, {**body, "errors": errors}
        return await self._run(principal, action, command, payload, asked_at_estops)

    async def _run(
        self,
        principal: Principal,
        action: str,
        command: Command,
        payload: Payload | None,
        asked_at_estops: int | None = None,
    ) -> Answer:
        note = AuditNote(principal.describe(), self.address, action, audit_label)
        try:
            outcome = await self.cell.command(
                command,
                source=f"{self.source}:{principal.name}",
                payload=payload,
                audit=note,
                asked_at_estops=asked_at_estops,
            )
        except (EventQueueFull, WorkerStopped, JournalUnavailable) as exc:
            self._audit(principal, action, "refused (503)", str(exc))
            state = self.cell.view.state.value
            body = {"accepted": False, "state": state, "message": str(exc)}
            return 503, {**body, "retry_after": RETRY_AFTER_S}
        status, body, _ = answer_of(outcome)
        if outcome.journal_problem is not None:  # not on record with the event: once more
            label = audit_label(outcome)
            self._audit(principal, action, label, f"event {outcome.event_id}: {outcome.message}")
        return status, body

    def refuse(self, principal: Principal | None, action: str, status: int, detail: str) -> Answer:
        log.info("MQTT command refused (%d): %s: %s", status, action, detail)
        self._audit(principal, action, f"refused ({status})", detail)
        return status, {"detail": detail}

    def _audit(self, principal: Principal | None, action: str, outcome: str, detail: str) -> None:
        journal = self.cell.journal
        if journal is None:
            return
        who = principal.describe() if principal else "anonymous"
        row = records.audit(time.time(), who, self.address, action, outcome, detail)
        journal.append([row], durable=False)
