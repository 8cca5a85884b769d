"""WebSocket /ws: a snapshot first, then every bus message, in order.

Each client is one bus subscription with a bounded buffer. A client that falls
behind (its buffer fills, or one send takes longer than SEND_TIMEOUT) is
closed with code 4001 and never delays the worker or the other clients.

Two roads to the socket, one at a time per client (server/core/infra/bus.py keeps
them apart): while the client's send task waits with nothing in hand, the bus
hands each new message to `_direct_sender`, which writes the shared frame to
the socket in the bus's delivery turn, with no task woken (at a thousand
clients, the wake of a task per client and message was the largest cost left
besides the socket write itself). When the frame cannot be written at once
(flow control paused the transport, the connection is closing), or while the
replay is being sent, the message waits in the buffer and the send task
takes it: the ordinary awaited send, bounded by SEND_TIMEOUT.

Resuming: the snapshot carries `boot`, the id of this server's numbering (seq
starts again at 1 in a new server process). A client that reconnects with
`?after_seq=N&boot=B` (the last seq it received, and the boot it came from) is
sent the messages it missed from the bus's ring of the last REPLAY_HISTORY
messages: the snapshot, marked `"replayed": K`, then those K messages (seq > N,
oldest first, all at or below the snapshot's seq), then live messages, with no
gap and no duplicate. The subscription and the ring are read in the same turn
of the loop, so they meet exactly at the snapshot's seq; the send loop also
drops any live message at or below the last seq sent. When the ring no longer
holds N + 1, or B is not this server's boot, the snapshot is marked
`"missed": M` instead (seq numbers the client will never see; for another
boot, every message this server published) and no replay follows: the
snapshot is the truth from then on. A `types=a,b` query parameter filters
from the start, replay included; a later subscribe message filters what is
published from then on.

`device` messages (live valve, flow, pressure and robot pose; see
server/views/live.py) are samples, not records: they carry no seq, are never
replayed, and are sent only to a client that names `device` in `types` (the
query or a subscribe message). Without `types` a client gets every record and
no samples, so its stream is what it was before samples existed.

Close codes (also in docs/api.md):
  1003  the client sent something that is not a valid JSON message, or the
        query is invalid (after_seq not a non-negative integer, after_seq
        without boot or boot without after_seq, after_seq beyond this
        server's last seq, unknown types)
  1009  the client sent a message over the size limit (enforced by the server)
  1013  too many clients (max_broadcast_clients), too many for this token
        (max_broadcast_clients_per_token), or only the slots kept for maintenance
        and admin are left (broadcast_clients_reserved); try again later
  4001  slow consumer: the client fell behind and was dropped
  4429  too many bad tokens or tickets from this address (auth_failure_limit):
        try again in the seconds the reason names
  4401  unauthorized: no valid one-shot ticket (POST /ws-ticket) or bearer token,
        or the token was revoked while the view was open (server/api/live_views.py)
  1012  the server is restarting or shutting down (sent by uvicorn)

Client → server messages (JSON): `{"type": "subscribe", "types": [...]}`
limits the message types sent from then on (null for all; `seq` then has gaps
for the filtered types); `{"type": "ping"}` is answered with `{"type": "pong"}`.
Dead connections are found by protocol-level pings (ws_ping_interval).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from starlette.datastructures import QueryParams

from server.api.access import authenticate_websocket, websocket_lockout
from server.api.live_views import CLOSE_UNAUTHORIZED, REVOKED_REASON, LiveViews
from server.api.ws_frames import FrameWriter, text_frame
from server.core.infra.bus import Bus, BusMessage, DirectConsumer, Subscription, SubscriptionClosed
from server.core.worker.view import CellView

log = logging.getLogger(__name__)
router = APIRouter()

MESSAGE_TYPES = (
    "state_changed",
    "progress",
    "error",
    "alert",
    "alert_cleared",
    "report",
    "device",
)
SEND_TIMEOUT = 5.0
ENCODED_CACHE = 64  # recent messages kept encoded; a client further behind re-encodes
MAX_SEQ_DIGITS = 18  # after_seq: any seq a server reaches, and still a 64-bit integer
MAX_BOOT_LENGTH = 64

CLOSE_INVALID = 1003
CLOSE_TOO_MANY = 1013
CLOSE_SLOW = 4001

Close = tuple[int | None, str]  # (close code or None for "just end", reason)


class ClientMessage(BaseModel):
    """What a client may send."""

    model_config = ConfigDict(extra="forbid")

    type: str = Field(pattern="^(subscribe|ping)$")
    types: list[str] | None = Field(None, max_length=len(MESSAGE_TYPES))


class InvalidQuery(ValueError):
    """The /ws query cannot be honoured; the message is the close reason."""


@dataclass(frozen=True, slots=True)
class Resume:
    """What the client asked for in the query: where to resume, and which types."""

    after_seq: int | None = None
    boot: str | None = None
    types: list[str] | None = None

    @classmethod
    def from_query(cls, params: QueryParams) -> Resume:
        """Validate `after_seq`, `boot` and `types`; raises InvalidQuery saying what is wrong."""
        for name in ("after_seq", "boot", "types"):
            if len(params.getlist(name)) > 1:
                raise InvalidQuery(f"give {name} once")
        raw_seq, boot = params.get("after_seq"), params.get("boot")
        after_seq = None
        if raw_seq is not None:
            # isascii: str.isdigit also accepts digits such as "²" that int() refuses.
            if not (raw_seq.isascii() and raw_seq.isdigit()) or len(raw_seq) > MAX_SEQ_DIGITS:
                raise InvalidQuery("after_seq must be a non-negative integer (the last seq seen)")
            after_seq = int(raw_seq)
        if boot is not None and not 0 < len(boot) <= MAX_BOOT_LENGTH:
            raise InvalidQuery(f"boot must be 1 to {MAX_BOOT_LENGTH} characters")
        # A seq means nothing without the numbering it came from: resuming on a bare
        # seq could replay a restarted server's messages as if they were the old ones.
        if (after_seq is None) != (boot is None):
            raise InvalidQuery("after_seq and boot go together (both from the last snapshot)")
        types = None
        if (raw_types := params.get("types")) is not None:
            types = [t for t in raw_types.split(",") if t]
            unknown = set(types) - set(MESSAGE_TYPES)
            if unknown:
                raise InvalidQuery(f"unknown message types: {', '.join(sorted(unknown))}"[:120])
        return cls(after_seq, boot, types)


class WebSocketHub:
    """Holds the live views (their limits, their revocation) and encodes each message once.

    Once: its JSON text, and the wire frame that carries it (server/api/ws_frames.py),
    shared by every client.
    """

    def __init__(
        self, max_clients: int, buffer: int, per_token: int = 10, reserved: int = 0
    ) -> None:
        self.views = LiveViews(max_clients, per_token, reserved)
        self.buffer = buffer
        self._encoded: OrderedDict[int, tuple[str, bytes]] = OrderedDict()
        self._newest = 0
        self._sample: tuple[BusMessage, str, bytes] | None = None  # the latest sample's

    @property
    def client_count(self) -> int:
        return self.views.count

    @property
    def max_clients(self) -> int:
        return self.views.max_clients

    @max_clients.setter
    def max_clients(self, value: int) -> None:
        self.views.max_clients = value

    def encode(self, message: BusMessage) -> str:
        """The message's JSON text, shared by every client (clients lag by a few at most)."""
        return self._encodings(message)[0]

    def frame(self, message: BusMessage) -> bytes:
        """The text frame carrying `encode(message)`, as written to every client's socket."""
        return self._encodings(message)[1]

    def _encodings(self, message: BusMessage) -> tuple[str, bytes]:
        if not message.numbered:  # a sample: the same one goes to every client that asked
            if self._sample is None or self._sample[0] is not message:
                text = json.dumps(message.as_dict())
                self._sample = (message, text, text_frame(text))
            return self._sample[1], self._sample[2]
        encoded = self._encoded.get(message.seq)
        if encoded is None:
            text = json.dumps(message.as_dict())
            encoded = (text, text_frame(text))
            if message.seq + ENCODED_CACHE <= self._newest:
                return encoded  # replayed to one client: not worth evicting a live one
            self._newest = max(self._newest, message.seq)
            self._encoded[message.seq] = encoded
            if len(self._encoded) > ENCODED_CACHE:
                self._encoded.popitem(last=False)
        return encoded


def _snapshot(view: CellView, bus: Bus) -> dict[str, Any]:
    return {"type": "snapshot", "seq": bus.last_seq, "boot": bus.boot, **view.live_snapshot()}


def _plan_replay(
    bus: Bus, resume: Resume, subscription: Subscription
) -> tuple[dict[str, int], list[BusMessage]]:
    """The snapshot's marks ("replayed" or "missed") and the messages to replay.

    Raises InvalidQuery for an after_seq this server never reached.
    """
    if resume.after_seq is None:
        return {}, []
    after_seq = resume.after_seq
    if resume.boot != bus.boot:  # another server process: its seq are not ours
        return {"missed": bus.last_seq}, []
    if after_seq > bus.last_seq:
        raise InvalidQuery(f"after_seq {after_seq} is beyond this server's last seq {bus.last_seq}")
    kept = bus.since(after_seq)
    if kept is None:  # older than the ring
        return {"missed": bus.last_seq - after_seq}, []
    # The filter given at connect time applies to the replay as to live messages.
    replay = [message for message in kept if subscription.wants(message.type)]
    return {"replayed": len(replay)}, replay


@router.websocket("/ws")
async def live(websocket: WebSocket) -> None:
    app = websocket.app
    hub: WebSocketHub = app.state.ws_hub
    cell = app.state.cell
    bus: Bus = cell.bus
    principal = authenticate_websocket(websocket)
    await websocket.accept()
    locked = websocket_lockout(websocket)
    if locked is not None:
        await websocket.close(*locked)
        return
    if principal is None:
        await websocket.close(
            CLOSE_UNAUTHORIZED,
            "unauthorized: open /ws with a ticket from POST /ws-ticket, or send a bearer token",
        )
        return
    try:
        resume = Resume.from_query(websocket.query_params)
    except InvalidQuery as invalid:
        await websocket.close(CLOSE_INVALID, str(invalid)[:120])
        return
    refusal = hub.views.refusal(principal)
    if refusal is not None:
        await websocket.close(CLOSE_TOO_MANY, refusal[:120])
        return
    view = hub.views.open(principal)
    if view.ended.done():  # its token was revoked during the handshake
        hub.views.close(view)
        await websocket.close(CLOSE_UNAUTHORIZED, REVOKED_REASON)
        return
    # Subscribe, take the snapshot and read the ring in one turn of the loop (no
    # await in between): the subscription receives every message after the
    # snapshot's seq, the ring holds every one up to it, so nothing falls between.
    subscription = bus.subscribe(hub.buffer, resume.types)
    try:
        snapshot = _snapshot(cell.view, bus)
        try:
            marks, replay = _plan_replay(bus, resume, subscription)
        except InvalidQuery as invalid:
            await websocket.close(CLOSE_INVALID, str(invalid)[:120])
            return
        await websocket.send_json({**snapshot, **marks})
        writer = FrameWriter.of(websocket)
        if writer is not None:
            subscription.take_directly(_direct_sender(hub, writer, snapshot["seq"]))
        sender = asyncio.create_task(
            _send_loop(websocket, subscription, hub, replay, snapshot["seq"], writer)
        )
        receiver = asyncio.create_task(_receive_loop(websocket, subscription))
        # `view.ended` is a plain future, set when the view's token is revoked.
        done, pending = await asyncio.wait(
            {sender, receiver, view.ended}, return_when=asyncio.FIRST_COMPLETED
        )
        # The client is ending either way: nothing more for it, by either road.
        subscription.close("client gone")
        for task in pending:
            task.cancel()
        await asyncio.gather(*pending, return_exceptions=True)
        close_code, reason = (view.ended if view.ended in done else next(iter(done))).result()
        if close_code is not None:
            # Bounded: a client that stopped reading may never take the close frame,
            # and must not hold its place among max_broadcast_clients (or a shutdown)
            # until the keepalive notices; the keepalive still ends the connection.
            with contextlib.suppress(Exception):
                async with asyncio.timeout(SEND_TIMEOUT):
                    await websocket.close(close_code, reason)
    except WebSocketDisconnect:
        pass
    finally:
        subscription.close("client gone")
        hub.views.close(view)


def _direct_sender(hub: WebSocketHub, writer: FrameWriter, snapshot_seq: int) -> DirectConsumer:
    """The bus's direct road to this client: write the shared frame now, or say it cannot."""
    frame = hub.frame

    def send_now(message: BusMessage) -> bool:
        if message.numbered and message.seq <= snapshot_seq:
            return True  # the snapshot covers it (never expected: see `live`)
        return writer.write(frame(message))

    return send_now


async def _send(
    websocket: WebSocket, hub: WebSocketHub, message: BusMessage, writer: FrameWriter | None
) -> Close | None:
    """Send one message; a Close when the connection must end, else None.

    The shared frame is written at once when the connection can take it without
    waiting (`writer`); otherwise the ordinary send, bounded by SEND_TIMEOUT.
    """
    if writer is not None and writer.write(hub.frame(message)):
        return None
    try:
        async with asyncio.timeout(SEND_TIMEOUT):  # no extra task per send, unlike wait_for
            await websocket.send_text(hub.encode(message))
    except TimeoutError:
        return CLOSE_SLOW, "slow consumer: a send did not complete in time"
    except (WebSocketDisconnect, RuntimeError, OSError):
        return None, ""
    return None


async def _send_loop(
    websocket: WebSocket,
    subscription: Subscription,
    hub: WebSocketHub,
    replay: Sequence[BusMessage],
    snapshot_seq: int,
    writer: FrameWriter | None = None,
) -> Close:
    """The replay (all at or below the snapshot's seq), then live messages above it."""
    for message in replay:
        if subscription.closed_reason is not None:
            break  # fell behind meanwhile: `get` below says so
        if (close := await _send(websocket, hub, message, writer)) is not None:
            return close
    while True:
        try:
            message = await subscription.get()
        except SubscriptionClosed as closed:
            return CLOSE_SLOW, f"{closed.reason}: you fell behind; reconnect and resync"
        if message.numbered and message.seq <= snapshot_seq:
            continue  # sent from the ring already (never expected: see `live`)
        if (close := await _send(websocket, hub, message, writer)) is not None:
            return close


async def _receive_loop(websocket: WebSocket, subscription: Subscription) -> Close:
    while True:
        try:
            raw = await websocket.receive_text()
        except WebSocketDisconnect:
            return None, ""
        except (KeyError, RuntimeError):  # a binary frame, or the socket went away
            return CLOSE_INVALID, "send JSON text messages only"
        try:
            message = ClientMessage.model_validate_json(raw)
        except ValidationError as exc:
            first = exc.errors()[0]
            where = ".".join(str(p) for p in first["loc"]) or "message"
            return CLOSE_INVALID, f"invalid message ({where}: {first['msg']})"[:120]
        if message.type == "ping":
            await websocket.send_json({"type": "pong"})
            continue
        unknown = set(message.types or ()) - set(MESSAGE_TYPES)
        if unknown:
            return CLOSE_INVALID, f"unknown message types: {', '.join(sorted(unknown))}"[:120]
        subscription.set_types(message.types)
        await websocket.send_json({"type": "subscribed", "types": message.types})
