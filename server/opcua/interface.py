"""The OPC UA server inside the cell server: started and stopped with the cell.

The tags follow the bus, not the cell: one bus subscription (its own bounded
buffer, like a WebSocket client's) is read by one task that writes each
message's values into the address space as it arrives, so a client's
subscription sees every transition, in order, stamped with when it happened,
and the worker never waits for OPC UA. A run's progress is the exception: it is
written at most every `plant_progress_interval`, the latest kept
(server/core/infra/paced_feed.py). The state comes from each
state_changed message's own snapshot, never from the live view, which may
already be a transition further on. Admin's KPIs are read from the journal
every `opcua_admin_interval` seconds, off the loop, the way GET /kpis reads
them (server/api/analytics.py: `shift_kpis`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from asyncua import Server, ua
from asyncua.common.callback import CallbackType

from server.bootstrap.cell import Cell
from server.common.errors import ConfigurationError
from server.core.infra.answers_in_flight import AnswersInFlight, after_answers
from server.core.infra.bus import BusMessage, SubscriptionClosed
from server.core.infra.paced_feed import PacedFeed
from server.core.machine.transitions import State
from server.opcua import address_space, server_info, tags
from server.opcua.address_space import CellNodes, data_value
from server.opcua.alarms import CellAlarms
from server.opcua.call_lane import CallLane
from server.opcua.certificate import application_uri, ensure_certificate
from server.opcua.identity import TokenUsers
from server.opcua.methods import CellMethods
from server.opcua.packml_feed import PackMLFeed
from server.opcua.packml_methods import PackMLMethods
from server.opcua.protection import CallGuard, PasswordGuard
from server.security.tokens import TokenStore
from server.settings.opcua import OpcUaSettings
from server.settings.plant import PlantSettings
from server.views.kpi_query import kpis_of

log = logging.getLogger(__name__)

BUS_BUFFER = 1024  # messages the follower may lag behind before it is dropped and catches up
FOLLOWED = ("state_changed", "progress", "error", "alert", "alert_cleared")


def endpoint_address(endpoint: str) -> tuple[str, int]:
    """The host and port an opc.tcp:// endpoint listens on."""
    url = urlparse(endpoint)
    if url.hostname is None or url.port is None:
        raise ConfigurationError(f"opcua_endpoint {endpoint!r} names no host and port")
    return url.hostname, url.port


def check_endpoint_free(endpoint: str) -> None:
    """Bind the endpoint's address once and let it go: a ConfigurationError naming it if
    that fails, before the server starts (a port in use, an address not on this host)."""
    host, port = endpoint_address(endpoint)
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
        for family, kind, proto, _, address in infos:
            with socket.socket(family, kind, proto) as probe:
                probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                probe.bind(address)
    except OSError as exc:
        raise ConfigurationError(
            f"the OPC UA endpoint {endpoint} cannot be served: {exc.strerror or exc}; "
            "choose a free port or an address of this host (opcua_endpoint)"
        ) from None


class OpcUaInterface:
    """asyncua's Server around one cell: address space, methods, the bus follower."""

    def __init__(
        self,
        cell: Cell,
        tokens: TokenStore,
        settings: OpcUaSettings,
        plant: PlantSettings,
        data_path: Path,
        *,
        answers: AnswersInFlight | None = None,
    ) -> None:
        assert settings.opcua_endpoint is not None
        self.cell = cell
        self.plant = plant
        self.data_path = data_path
        self.answers = answers  # the commands being answered, which go first
        self.settings = settings
        self.endpoint = settings.opcua_endpoint
        server_info.quiet_asyncua(settings.opcua_log_level)
        self.server = Server(user_manager=TokenUsers(tokens))  # type: ignore[arg-type]
        self.methods = CellMethods(self.server, cell, tokens)
        self.alarms = CellAlarms(self.server, cell, tokens, answers)
        self.calls = CallLane(self.server, self.methods.is_stop, cell.stops_now)
        self.tokens = tokens
        self.nodes: CellNodes | None = None
        self.packml: PackMLFeed | None = None  # the PackML state machines, Status and Admin
        self._counts: dict[str, int] = {}
        self._feed: PacedFeed | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._snapshot: dict[str, Any] = {}
        self._progress: dict[str, Any] | None = None
        self._seq = 0
        self._written: dict[str, object] = {}

    async def start(self) -> None:
        settings = self.settings
        server = self.server
        await server.init()
        # A password only where nobody else can read it (server/opcua/protection.py).
        PasswordGuard(server, self.cell, self.tokens).install()
        # A session's calls side by side, a stop ahead of them (server/opcua/call_lane.py).
        self.calls.install()
        server.set_endpoint(self.endpoint)
        server.set_server_name(f"glue cell {self.plant.cell_id}")
        await server_info.set_build_info(server)
        await server.set_application_uri(application_uri(self.plant.cell_id))
        certificate, key = await asyncio.to_thread(
            ensure_certificate, self.data_path, self.plant.cell_id
        )
        await server.load_certificate(str(certificate))
        await server.load_private_key(str(key))
        policies = [
            ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
            ua.SecurityPolicyType.Basic256Sha256_Sign,
        ]
        if settings.opcua_allow_unsecured:
            policies.insert(0, ua.SecurityPolicyType.NoSecurity)
        server.set_security_policy(
            policies, permission_ruleset=CallGuard(server, self.cell, self.tokens)
        )
        server.set_identity_tokens([ua.AnonymousIdentityToken, ua.UserNameIdentityToken])
        self.nodes = nodes = await address_space.build(server, self.plant.cell_id)
        await self.methods.add(nodes.cell, nodes.cell_id, nodes.namespace)
        self.packml = PackMLFeed(server, nodes)
        await PackMLMethods(server, self.cell, self.methods, self.packml).add(nodes)
        await self.packml.write_constants(self.plant.cell_id)
        await self.alarms.install(server.get_node(nodes.cell), nodes.cell_id, nodes.namespace)
        # Each session reads its own UserExecutable: false where a call would be refused.
        server.subscribe_server_callback(CallbackType.PostRead, self.methods.user_executable)
        # Subscribe before the first values are written: nothing falls between the two.
        view = self.cell.view
        subscription = self.cell.bus.subscribe(BUS_BUFFER, FOLLOWED)
        self._feed = PacedFeed(subscription, self.plant.plant_progress_interval)
        self._seq = self.cell.bus.last_seq
        # The worker's verdicts, as they are made: PackML's acting states (packml_feed.py).
        self.cell.worker.decisions.add(self.packml.decided)  # type: ignore[union-attr]
        self.alarms.subscribe()
        await self._write_state(view.snapshot(), None)
        try:
            await server.start()
        except OSError as exc:
            subscription.close()
            await self.alarms.stop()
            raise ConfigurationError(
                f"the OPC UA endpoint {self.endpoint} cannot be served: {exc.strerror or exc}; "
                "choose a free port or an address of this host (opcua_endpoint)"
            ) from None
        await self.alarms.start()
        self._tasks = [
            asyncio.create_task(self._follow(), name="opcua-follower"),
            asyncio.create_task(self._refresh_admin(), name="opcua-admin"),
        ]
        log.info("OPC UA served at %s (cell %s)", self.endpoint, self.plant.cell_id)

    async def stop(self) -> None:
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._tasks = []
        if self.packml is not None:
            if self.cell.worker is not None:
                self.cell.worker.decisions.remove(self.packml.decided)
            await self.packml.stop()
        await self.alarms.stop()
        await self.calls.close()
        if self._feed is not None:
            self._feed.subscription.close()
        await self.server.stop()

    # --- following the bus --------------------------------------------------------------

    def session_count(self) -> int:
        """The client sessions open on the server now (GET /metrics: glue_cell_opcua_sessions).

        asyncua keeps them in a private map, registered when a session is created and
        removed when it closes or times out; it offers no public count.
        """
        return len(getattr(self.server.iserver, "_external_sessions", {}))

    async def _follow(self) -> None:
        # A run's progress at most every plant_progress_interval, the latest kept
        # (server/core/infra/paced_feed.py says why); transitions and faults as they come.
        feed = self._feed
        assert feed is not None
        while True:
            try:
                message = await feed.get()
            except SubscriptionClosed as closed:
                # Dropped as a slow consumer: catch up from the live view, go on.
                log.warning("OPC UA tags fell behind the bus (%s); catching up", closed.reason)
                feed.resubscribe(self.cell.bus.subscribe(BUS_BUFFER, FOLLOWED))
                self._seq = self.cell.bus.last_seq
                await self._write_state(self.cell.view.snapshot(), None)
                continue
            if message.type == "state_changed" and self.cell.journal is not None:
                # After the transition's own commit, as the MQTT link does (its
                # `_after_its_commit` says why): the command is answered first.
                await self.cell.journal.caught_up()
            await after_answers(self.answers)  # and once its answer has gone
            try:
                await self._apply(message)
            except Exception:  # a tag not written must not end the follower
                log.exception("OPC UA: could not write the tags of bus message %d", message.seq)

    async def _apply(self, message: BusMessage) -> None:
        self._seq = message.seq
        assert self.packml is not None
        if message.type == "state_changed":
            await self.packml.settled(message.data, message.time)
            await self._write_snapshot(message.data["snapshot"], None, message.time)
        elif message.type == "alert":  # a warning: Admin.Warning
            self.packml.warned(message.data)
            await self.packml.write_admin(self._snapshot, self._counts, message.time)
        elif message.type == "alert_cleared":  # its cause gone: out of Admin.Warning
            self.packml.warning_cleared(message.data)
            await self.packml.write_admin(self._snapshot, self._counts, message.time)
        elif message.type == "progress":
            # The run's steps in the state they belong to (the state_changed snapshot
            # that enters a state is taken before its run starts, so it names no run yet):
            # a spray run's waypoints and a calibration's steps alike.
            data = message.data
            if data.get("run_id") and data.get("state") == self._snapshot.get("state"):
                self._progress = dict(data)
                await self.packml.progressed(State(data["state"]), message.time)
                await self._write_cell_state(message.time)
        else:  # a fault: the devices' health has changed
            await self._write_cell_state(message.time)

    async def _write_state(
        self, snapshot: dict[str, Any], progress: dict[str, Any] | None, at: float | None = None
    ) -> None:
        """Everything from the cell's snapshot, PackML's state where the cell is (the
        start, a catch-up after the follower was dropped)."""
        assert self.packml is not None
        at = at if at is not None else snapshot.get("since")
        await self.packml.begin(State(snapshot["state"]), at)
        await self._write_snapshot(snapshot, progress, at)

    async def _write_snapshot(
        self, snapshot: dict[str, Any], progress: dict[str, Any] | None, at: float | None
    ) -> None:
        assert self.packml is not None
        self._snapshot, self._progress = snapshot, progress
        at = at if at is not None else snapshot.get("since")
        await self._write("Status.CellStateName", snapshot["state"], at)
        await self.packml.write_admin(snapshot, self._counts, at)
        await self._write_cell_state(at)

    async def _write_cell_state(self, at: float | None = None) -> None:
        devices = self.cell.view.health()["devices"]
        document = tags.cell_state(self._snapshot, self._progress, devices, self._seq)
        await self._write("CellState", tags.encode(document), at)

    async def _write(self, path: str, value: object, at: float | None) -> None:
        """Write a tag; an unchanged value is not written again (no notification for it).
        CellState carries the bus message's seq, so each transition changes it."""
        if path in self._written and tags.same(self._written[path], value):
            return
        assert self.nodes is not None
        self._written[path] = value
        kind = self.nodes.types[path]
        await self.server.write_attribute_value(
            self.nodes.variables[path], data_value(kind, value, at)
        )

    # --- Admin: the KPIs of the shift ------------------------------------------------------

    async def _refresh_admin(self) -> None:
        while True:
            try:
                kpis = await kpis_of(self.cell)
                for name, figure in tags.admin_figures(kpis).items():
                    await self._write(f"Admin.{name}", figure, None)
                self._counts = tags.admin_counts(kpis)
                if self.packml is not None:
                    await self.packml.write_admin(self._snapshot, self._counts, None)
                    await self.packml.write_times()
                await self._write_cell_state()  # the devices' health, between messages
            except Exception:
                log.exception("OPC UA: could not refresh the Admin figures")
            await asyncio.sleep(self.settings.opcua_admin_interval)
