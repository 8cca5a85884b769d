"""Following /ws: an async iterator over the cell's messages that survives reconnects,
resuming from the last `seq` seen and the server's `boot` (see MessageStream).
"""

from __future__ import annotations

import asyncio
import json
import random
from collections.abc import AsyncGenerator, AsyncIterator, Iterable
from types import TracebackType
from typing import TYPE_CHECKING, Any, Self

from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI

from clients.client.config import USER_AGENT, WS_MAX_MESSAGE_BYTES
from clients.client.errors import (
    Busy,
    CellError,
    Forbidden,
    ServerError,
    Unauthorized,
    Unreachable,
)

if TYPE_CHECKING:
    from clients.client.async_client import AsyncCellClient


def _refusal(code: int | None, reason: str) -> CellError:
    """The typed error for a /ws close before the snapshot (close codes in docs/api.md)."""
    message = f"/ws closed ({code}): {reason}"
    if code == 4401:
        return Unauthorized(message, status_code=code)
    if code == 1013:  # too many clients
        return Busy(message, retry_after=1.0, status_code=code)
    return Unreachable(message, status_code=code)


class MessageStream:
    """An async iterator over /ws messages that survives reconnects.

    Each (re)connection takes a fresh one-shot ticket (POST /ws-ticket). The first
    item is the server's snapshot, then every message in `seq` order. When the
    connection drops (slow consumer 4001, server restart, network) the stream
    waits (backoff doubling from `initial_backoff` to `max_backoff`, with jitter)
    and reconnects with `after_seq` (the last seq seen) and `boot` (the server's
    numbering), and yields the new snapshot as
    `{"type": "snapshot", "resumed": True, "missed": N, ...}`:

    - the server still held every message after the last one seen (its ring of
      recent messages): N is 0, the snapshot has `"replayed": K`, and the K
      messages that went by follow it, oldest first, then live ones. So every
      message is yielded exactly once. The replayed ones are older than the
      snapshot (their seq is at or below its seq): a consumer that applied them
      all is where the snapshot is, and may ignore the snapshot;
    - the gap is older than the ring: N seq numbers went by unseen and none
      follow; resynchronise from the snapshot;
    - the server restarted (another `boot`; seq starts again at 1): N counts the
      new server's messages and `restarted` is True.

    Against a server without replay (no `boot` in its snapshot) N is computed
    here, as the difference of seq numbers.

    `types` filters on this side, so `missed` stays exact and `replayed` counts
    every type; snapshots always pass.
    Errors while making the *first* connection are raised (Unreachable,
    Unauthorized, Busy for close 1013 "too many clients", ...); afterwards only
    Unauthorized and Forbidden from the ticket request are (a revoked token will
    not come back), everything else is retried until the consumer stops iterating.

    Stop with `break` (the socket is closed when the stream is collected), or
    deterministically with `aclose()` / `async with stream:`.
    """

    def __init__(
        self,
        client: AsyncCellClient,
        types: Iterable[str] | None,
        *,
        reconnect: bool,
        initial_backoff: float,
        max_backoff: float,
    ) -> None:
        self._client = client
        self.types = frozenset(types) if types is not None else None
        self.reconnect = reconnect
        self.initial_backoff = initial_backoff
        self.max_backoff = max_backoff
        self.last_seq: int | None = None
        self.boot: str | None = None  # the server's numbering that last_seq belongs to
        self.reconnects = 0
        self.last_close: tuple[int | None, str] | None = None  # (code, reason) of the last drop
        self._generator = self._run()

    def __aiter__(self) -> AsyncIterator[dict[str, Any]]:
        return self

    async def __anext__(self) -> dict[str, Any]:
        return await self._generator.__anext__()

    async def aclose(self) -> None:
        await self._generator.aclose()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()

    def _wanted(self, message: dict[str, Any]) -> bool:
        return self.types is None or message.get("type") in self.types

    async def _open(self) -> ClientConnection:
        ticket = await self._client.ws_ticket()
        # Resume where we were: the server replays what came after last_seq, if it can.
        if self.last_seq is not None and self.boot is not None:
            url = self._client.ws_url(ticket, after_seq=self.last_seq, boot=self.boot)
        else:
            url = self._client.ws_url(ticket)
        # wss: the server's certificate is checked as https checks it (the client's CA
        # file); websockets refuses an ssl context for a ws:// URL.
        tls = self._client.tls if url.startswith("wss:") else None
        try:
            return await connect(
                url,
                ssl=tls,
                open_timeout=self._client.timeout,
                close_timeout=2,
                max_size=WS_MAX_MESSAGE_BYTES,
                user_agent_header=USER_AGENT,
            )
        except (OSError, TimeoutError, InvalidHandshake, InvalidURI) as exc:
            raise Unreachable(f"cannot open {url.split('?')[0]}: {exc}") from exc

    def _resumed(self, snapshot: dict[str, Any]) -> dict[str, Any]:
        """Mark a snapshot after a reconnect with how much went by unseen."""
        seq = int(snapshot.get("seq", 0))
        assert self.last_seq is not None
        marks: dict[str, Any] = {"resumed": True}
        boot = snapshot.get("boot")
        other_boot = self.boot is not None and boot is not None and boot != self.boot
        if other_boot or seq < self.last_seq:  # a new server process: numbering started again
            marks["missed"] = int(snapshot.get("missed", seq))
            marks["restarted"] = True
        elif "replayed" in snapshot:  # everything since last_seq follows this snapshot
            marks["missed"] = 0
        elif "missed" in snapshot:  # the server could not fill the gap
            marks["missed"] = int(snapshot["missed"])
        else:  # a server without replay
            marks["missed"] = seq - self.last_seq
        return {**snapshot, **marks}

    async def _run(self) -> AsyncGenerator[dict[str, Any], None]:
        backoff = self.initial_backoff
        connected_once = False
        while True:
            try:
                websocket = await self._open()
            except (Unauthorized, Forbidden):
                raise
            except CellError:
                if not connected_once or not self.reconnect:
                    raise
                await self._pause(backoff)
                backoff = min(backoff * 2, self.max_backoff)
                continue
            try:
                async with websocket:
                    snapshot = json.loads(await websocket.recv())
                    if snapshot.get("type") != "snapshot":
                        raise ServerError(f"/ws did not start with a snapshot: {snapshot!r:.200}")
                    if connected_once:
                        self.reconnects += 1
                        snapshot = self._resumed(snapshot)
                    connected_once = True
                    backoff = self.initial_backoff
                    if snapshot.get("missed") != 0 or "replayed" not in snapshot:
                        self.last_seq = int(snapshot.get("seq", 0))
                    # else last_seq stays: the replay that follows starts at last_seq + 1.
                    self.boot = snapshot.get("boot")
                    yield snapshot
                    async for raw in websocket:
                        message = json.loads(raw)
                        seq = message.get("seq")
                        if isinstance(seq, int):
                            if self.last_seq is not None and seq <= self.last_seq:  # seen before
                                continue
                            self.last_seq = seq
                        if self._wanted(message):
                            yield message
                self.last_close = (websocket.close_code, websocket.close_reason or "")
            except ConnectionClosed as closed:
                received = closed.rcvd
                code = received.code if received else None
                reason = (received.reason if received else "") or "connection lost"
                self.last_close = (code, reason)
                if not connected_once:  # refused before the first snapshot: say why
                    raise _refusal(code, reason) from closed
                if code == 1003:
                    # The resume request itself was refused (never expected): start
                    # afresh next time rather than be refused on every attempt.
                    self.boot = None
            except (OSError, TimeoutError, ValueError) as exc:
                self.last_close = (None, f"{type(exc).__name__}: {exc}")
                if not connected_once:
                    raise Unreachable(f"/ws failed: {self.last_close[1]}") from exc
            if not self.reconnect:
                return
            await self._pause(backoff)
            backoff = min(backoff * 2, self.max_backoff)

    @staticmethod
    async def _pause(backoff: float) -> None:
        # Jitter, so a fleet of dashboards does not reconnect in lockstep after a restart.
        await asyncio.sleep(backoff * random.uniform(0.8, 1.2))
