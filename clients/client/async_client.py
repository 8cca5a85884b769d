"""The asyncio client, for dashboards and bridges: the blocking client's methods,
plus `messages()`, which follows /ws across reconnects.
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import Iterable
from types import TracebackType
from typing import Any, Self, TypeVar

import httpx

from clients.client import builders
from clients.client.builders import Call
from clients.client.config import (
    DEFAULT_URL,
    KEEPALIVE_EXPIRY_S,
    default_headers,
    normalize_url,
    trust,
)
from clients.client.errors import CommandResult
from clients.client.stream import MessageStream
from clients.client.wait import StateWait

T = TypeVar("T")


class AsyncCellClient:
    """Asyncio client (httpx.AsyncClient), the same methods as CellClient, plus `messages`."""

    def __init__(
        self,
        base_url: str = DEFAULT_URL,
        token: str | None = None,
        *,
        timeout: float = 10.0,
        ca_file: str | os.PathLike[str] | None = None,
        keepalive_expiry: float = KEEPALIVE_EXPIRY_S,
    ) -> None:
        """`ca_file`: the CA certificate(s), PEM, that the server's https certificate must
        chain to (a plant's own CA); None trusts the usual public CAs. OSError or
        ssl.SSLError here when it cannot be read. `keepalive_expiry`: seconds an idle
        connection is kept (config.KEEPALIVE_EXPIRY_S), below the server's
        http_keepalive_timeout."""
        self.base_url = normalize_url(base_url)
        self.timeout = timeout
        self.tls = trust(ca_file)
        self.token = token
        self._http = httpx.AsyncClient(
            base_url=self.base_url,
            headers=default_headers(token),
            timeout=timeout,
            verify=self.tls if self.tls is not None else True,
            limits=httpx.Limits(keepalive_expiry=keepalive_expiry),
        )

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    async def _request(self, call: Call[Any]) -> httpx.Response:
        return await self._http.request(call.method, call.path, json=call.json, params=call.params)

    async def _send(self, call: Call[T]) -> T:
        try:
            try:
                response = await self._request(call)
            except httpx.TransportError as exc:
                if not builders.may_send_again(call, exc):
                    raise
                response = await self._request(call)
        except httpx.TransportError as exc:
            raise builders.unreachable(self.base_url, exc, self.timeout) from exc
        return builders.read(call, response)

    async def start(
        self, workpiece_id: str | None = None, contour_matching: bool = True
    ) -> CommandResult:
        """Start spraying (IDLE → EXECUTING_TRAJECTORY)."""
        return await self._send(builders.start(workpiece_id, contour_matching))

    async def pause(self) -> CommandResult:
        """Stop the trajectory where it is, glue off; resume continues the same segment."""
        return await self._send(builders.command("pause"))

    async def resume(self) -> CommandResult:
        """Continue a paused trajectory from where it held."""
        return await self._send(builders.command("resume"))

    async def cancel(self) -> CommandResult:
        """Stop the running operation at once and return to IDLE."""
        return await self._send(builders.command("cancel"))

    async def estop(self, reason: str | None = None) -> CommandResult:
        """Software stop: valve closed and robot stopped, then ERROR (any role)."""
        return await self._send(builders.estop(reason))

    async def reset(self) -> CommandResult:
        """Leave ERROR for IDLE once every device answers (maintenance role)."""
        return await self._send(builders.command("reset"))

    async def home(self) -> CommandResult:
        """Send the robot to its safe position, in IDLE (maintenance role)."""
        return await self._send(builders.command("home"))

    async def jog(self, axis: str, distance_mm: float) -> CommandResult:
        """Move the robot one bounded step along x, y or z, in IDLE (maintenance role)."""
        return await self._send(builders.jog(axis, distance_mm))

    # production orders

    async def create_order(self, workpiece_id: str, quantity: int) -> dict[str, Any]:
        """A production order of `quantity` good parts (operator role): runs or queues."""
        return await self._send(builders.create_order(workpiece_id, quantity))

    async def orders(self, state: str | None = None) -> dict[str, Any]:
        """The orders, newest first, and the active one's id."""
        return await self._send(builders.orders(state))

    async def order(self, order_id: str) -> dict[str, Any]:
        """One order: state, reason, counts."""
        return await self._send(builders.order(order_id))

    async def close_order(self, order_id: str) -> dict[str, Any]:
        """End an order before its quantity (operator role)."""
        return await self._send(builders.close_order(order_id))

    async def resume_order(self, order_id: str) -> dict[str, Any]:
        """Continue a held order from IDLE (operator role)."""
        return await self._send(builders.resume_order(order_id))

    async def order_report(self, order_id: str) -> dict[str, Any]:
        """Every part of the order: run, times, verdict, precision, glue."""
        return await self._send(builders.order_report(order_id))

    async def order_report_csv(self, order_id: str) -> str:
        """The order's report as CSV text."""
        return await self._send(builders.order_report_csv(order_id))

    async def markers(self) -> dict[str, Any]:
        """The marker layout in force, the draft being taught, the robot's last pose."""
        return await self._send(builders.markers())

    async def teach_marker(self, marker: int) -> dict[str, Any]:
        """Record the tool's x, y as marker `marker` in the draft (maintenance role)."""
        return await self._send(builders.teach_marker(marker))

    async def apply_markers(self) -> dict[str, Any]:
        """Put the draft layout in force once all nine pass the check (maintenance role)."""
        return await self._send(builders.apply_markers())

    async def settings(self) -> dict[str, Any]:
        """The settings in force, `sources` (where each comes from) and `runtime_settings`
        (those a change applies at once) (admin role)."""
        return await self._send(builders.settings())

    async def change_settings(self, **values: Any) -> dict[str, Any]:
        """Change runtime settings at once and keep them over a restart (admin role)."""
        return await self._send(builders.change_settings(values))

    async def calibrate_robot(self) -> CommandResult:
        """Fit the image → robot map from the ArUco markers (maintenance role)."""
        return await self._send(builders.command("calibrate-robot"))

    async def calibrate_camera(self) -> CommandResult:
        """Calibrate the camera's intrinsics from chessboard views (maintenance role)."""
        return await self._send(builders.command("calibrate-camera"))

    async def create_workpiece(
        self, name: str | None = None, workpiece_id: str | None = None, if_new: bool = False
    ) -> CommandResult:
        """Capture the part on the table into the library (`if_new`: only if it matches no
        stored part; the run's result says which it matches)."""
        return await self._send(builders.create_workpiece(name, workpiece_id, if_new))

    async def state(self) -> dict[str, Any]:
        """GET /state: state, operation and progress, the fault if any."""
        return await self._send(builders.state())

    async def workpieces(self) -> list[dict[str, Any]]:
        """The workpiece library."""
        return await self._send(builders.workpieces())

    async def history(self, limit: int = 20) -> list[dict[str, Any]]:
        """The latest `limit` transitions, newest first."""
        return await self._send(builders.history(limit))

    async def purge(self) -> CommandResult:
        """Purge the glue line at the purge position, in IDLE (maintenance role)."""
        return await self._send(builders.command("purge"))

    async def maintenance(self) -> dict[str, Any]:
        """Wear counters, the maintenance schedule, pot life and glue level."""
        return await self._send(builders.maintenance())

    async def maintenance_done(self, item: str) -> dict[str, Any]:
        """Mark a maintenance item done: its intervals start again (maintenance role)."""
        return await self._send(builders.maintenance_done(item))

    async def glue_refill(self) -> dict[str, Any]:
        """The glue reservoir was refilled: its level is full again (maintenance role)."""
        return await self._send(builders.glue_refill())

    async def kpis(self) -> dict[str, Any]:
        """The current shift's KPIs and OEE."""
        return await self._send(builders.kpis())

    async def reports(self, period: str | None = None, limit: int = 50) -> list[dict[str, Any]]:
        """The shift and daily reports kept, newest first (`period`: shift or day)."""
        return await self._send(builders.reports(period, limit))

    async def report(self, report_id: int) -> dict[str, Any]:
        """One shift or daily report, whole."""
        return await self._send(builders.report(report_id))

    async def report_html(self, report_id: int) -> str:
        """One report as a printable HTML page with its charts."""
        return await self._send(builders.report_html(report_id))

    async def health(self) -> dict[str, Any]:
        """Each device's link and the worker's figures (needs no token)."""
        return await self._send(builders.health())

    async def allowed(self, command: str) -> dict[str, Any]:
        """Whether `command` would be accepted now: `allowed`, `state`, `reason`."""
        return await self._send(builders.allowed(command))

    async def wait_for_state(
        self,
        state: str,
        timeout: float,
        *,
        poll_interval: float = 0.1,
        fail_on: Iterable[str] = ("ERROR",),
    ) -> dict[str, Any]:
        """Poll GET /state until the cell is in `state` (see CellClient.wait_for_state)."""
        wait = StateWait(state, timeout, fail_on)
        while True:
            if wait.reached(await self.state()):
                assert wait.last is not None
                return wait.last
            remaining = wait.remaining()
            if remaining <= 0:
                raise wait.expired()
            await asyncio.sleep(min(poll_interval, remaining))

    async def ws_ticket(self) -> str:
        """A one-shot ticket for /ws (valid a few seconds, usable once)."""
        return await self._send(builders.ws_ticket())

    def ws_url(self, ticket: str, *, after_seq: int | None = None, boot: str | None = None) -> str:
        """The /ws address for `ticket`, under the same base URL (keeps a path prefix).

        With `after_seq` and `boot` (the last seq received and the snapshot's boot;
        one means nothing without the other) the server replays what came after.
        """
        return builders.ws_url(self.base_url, ticket, after_seq=after_seq, boot=boot)

    def messages(
        self,
        types: Iterable[str] | None = None,
        *,
        reconnect: bool = True,
        initial_backoff: float = 0.2,
        max_backoff: float = 5.0,
    ) -> MessageStream:
        """Follow /ws: the snapshot, then every message (of `types`, if given), in seq order.

        See MessageStream for what happens across reconnects.
        """
        return MessageStream(
            self,
            types,
            reconnect=reconnect,
            initial_backoff=initial_backoff,
            max_backoff=max_backoff,
        )
