"""The cell as a Sparkplug B edge node: births, deaths, data on change, rebirth, commands.

A connection of its own to the MQTT link's broker (same URL, user, password, CA),
because Sparkplug's NDEATH must be the connection's last will, carrying the bdSeq
of the NBIRTH sent on that connection, and an MQTT connection has one will: the
link's is its `status`. Each connection takes the next bdSeq (0 to 255, then 0):
its NDEATH will is registered with it at connect, its NBIRTH names it, and a clean
stop publishes the same NDEATH itself before it leaves. The next bdSeq is kept in
the data directory (`sparkplug.bdseq`) across restarts: a killed server's will
reaches the host up to 1.5 keep-alives late, perhaps after the restarted server's
NBIRTH, and only a different bdSeq tells the host that death is the old session's.
Within a session `seq` runs 0 (the NBIRTH) to 255 and wraps, one step a message.

Nothing is buffered while the broker is away: on each connection the node
subscribes to its NCMD and DCMD topics, then sends NBIRTH and DBIRTH with every
metric's present value, which is all a host needs (Sparkplug's own rule). DDATA
goes when a metric changes: at once on a transition (after its commit, and once
no command's answer is in flight, as the MQTT link), and on a look at the health
every second and at the KPIs every `mqtt_kpis_interval` and after each run ends.
An NCMD `Node Control/Rebirth` true sends both births again (same bdSeq, seq from 0).

A DCMD `Command/<Name>` true runs that command through the MQTT command door
(server/mqtt/commands.py: `CommandDoor.execute`), as the principal of the token
`sparkplug_command_token_id` names: the catalogue's role, body model, stop rule and
audit, as every door. Sparkplug payloads carry no signature, so commands are off
unless that setting names a token, and a DCMD older than `mqtt_command_max_age`
(its payload's timestamp) is refused as stale: a start queued somewhere must not
start the cell later. Each command is a task of its own (an e-stop never waits
behind one), and its answer shows in DDATA (`Command/Last/...`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import ssl
import time
from collections.abc import Awaitable, Callable
from typing import Any

import aiomqtt

from server.bootstrap.cell import Cell
from server.core.infra.answers_in_flight import AnswersInFlight, after_answers
from server.core.infra.bus import SubscriptionClosed
from server.core.machine.transitions import Command, State
from server.core.worker.runs import RunEnded
from server.mqtt.commands import CommandDoor
from server.mqtt.link import broker_address
from server.mqtt.sparkplug import metrics as sp
from server.mqtt.sparkplug.payload import Metric, Payload, PayloadError, decode, encode
from server.security.tokens import TokenStore
from server.settings.model import Settings

log = logging.getLogger(__name__)

FIRST_BACKOFF_S = 0.1
TICK_S = 1.0  # how often the devices' links are looked at for a change
STOP_FLUSH_S = 2.0  # at a clean stop, how long the NDEATH may take to go
BUS_BUFFER = 256
BD_SEQ_FILE = "sparkplug.bdseq"  # the next connection's bdSeq, in the data directory


def now_ms() -> int:
    return int(time.time() * 1000)


class SparkplugNode:
    """Publishes the cell as a Sparkplug B edge node and, if enabled, runs its DCMDs."""

    def __init__(
        self,
        settings: Settings,
        cell: Cell,
        *,
        packml_state: Callable[[State], int],
        health: Callable[[], dict[str, Any]],
        kpis: Callable[[], Awaitable[dict[str, Any]]],
        tokens: TokenStore,
        door: CommandDoor | None = None,
        answers: AnswersInFlight | None = None,
    ) -> None:
        assert settings.mqtt_url is not None and settings.sparkplug_group is not None
        self.settings = settings
        self.cell = cell
        self.host, self.port, self.tls = broker_address(settings.mqtt_url)
        self.topics = sp.Topics(
            settings.sparkplug_group, settings.sparkplug_edge_node or settings.cell_id
        )
        self._packml_state = packml_state
        self._health = health
        self._kpis = kpis
        self._tokens = tokens
        self._door = door
        self._answers = answers
        self._client: aiomqtt.Client | None = None
        self._lock = asyncio.Lock()  # one message at a time: seq is their order
        self._bd_seq_file = settings.data_path / BD_SEQ_FILE
        self._bd_seq = 0  # this connection's (the will registered with it)
        self._seq = 0  # the next message's
        self._told: dict[str, Any] = {}  # what the host was last told, metric by metric
        self._kpi_values: dict[str, Any] | None = None
        self._last: dict[str, Any] = {}  # the last command's answer (Command/Last/...)
        self._tasks: list[asyncio.Task[None]] = []
        self._in_flight: set[asyncio.Task[None]] = set()
        self._stopping = False
        self._last_error: str | None = None
        self.births = 0  # NBIRTHs sent since start (for /health and the tests)

    @property
    def commands(self) -> bool:
        return self._door is not None and self.settings.sparkplug_command_token_id is not None

    # --- life ----------------------------------------------------------------------

    def start(self) -> None:
        """Subscribe to the bus and start connecting; returns at once."""
        subscription = self.cell.bus.subscribe(BUS_BUFFER, types=("state_changed",))
        self.cell.view.on_run_ended(self._run_ended)
        self._tasks = [
            asyncio.create_task(self._feed(subscription), name="sparkplug-feed"),
            asyncio.create_task(self._connection(), name="sparkplug-connection"),
            asyncio.create_task(self._ticker(), name="sparkplug-ticker"),
        ]
        log.info(
            "Sparkplug B: edge node %s/%s on %s:%d (commands %s)",
            self.topics.group,
            self.topics.edge_node,
            self.host,
            self.port,
            "on" if self.commands else "off",
        )

    async def stop(self) -> None:
        """Say NDEATH (this session's bdSeq) if the broker is there, then leave cleanly."""
        self._stopping = True
        feed, connection, ticker = self._tasks or (None, None, None)
        for task in (feed, ticker, *self._in_flight):
            if task is not None:
                task.cancel()
        client = self._client
        if client is not None:
            death = encode(Payload(now_ms(), (sp.bd_seq_metric(self._bd_seq, now_ms()),)))
            with contextlib.suppress(aiomqtt.MqttError, TimeoutError):
                async with asyncio.timeout(STOP_FLUSH_S):
                    await client.publish(self.topics.node("NDEATH"), death, qos=1)
        if connection is not None:
            connection.cancel()
        await asyncio.gather(*self._tasks, *self._in_flight, return_exceptions=True)
        self._tasks = []

    def health(self) -> dict[str, Any]:
        """The node as /health could show it."""
        return {
            "connected": self._client is not None,
            "edge_node": f"{self.topics.group}/{self.topics.edge_node}",
            "bd_seq": self._bd_seq,
            "births": self.births,
            "commands": self.commands,
        }

    # --- what the host is told --------------------------------------------------------

    def _sample(self, snapshot: dict[str, Any] | None = None) -> dict[str, Any]:
        view = self.cell.view
        snapshot = snapshot or view.snapshot()
        run = view.current_run() if view.since == snapshot["since"] else None
        packml = self._packml_state(State(snapshot["state"]))
        devices = self._health().get("devices", {})
        values = sp.sample(snapshot, run, packml, self._kpi_values, devices)
        if self.commands:
            values.update({name: self._last.get(name) for name in sp.LAST_METRICS})
        return values

    async def _send(self, topic: str, metrics: tuple[Metric, ...], *, birth: bool = False) -> None:
        """One message at QoS 0 (Sparkplug's), numbered; dropped while the broker is away
        (the next connection's births carry the present)."""
        client = self._client
        if client is None:
            return
        if birth:
            self._seq = 0
        payload = encode(Payload(now_ms(), metrics, seq=self._seq))
        self._seq = (self._seq + 1) % sp.SEQ_LIMIT
        await client.publish(topic, payload, qos=0)

    async def _birth(self) -> None:
        """NBIRTH then DBIRTH, with every metric's value now."""
        async with self._lock:
            at = now_ms()
            values = self._sample()
            await self._send(
                self.topics.node("NBIRTH"), sp.node_birth_metrics(self._bd_seq, at), birth=True
            )
            metrics = sp.birth_metrics(values, at, commands=self.commands, last=self._last)
            await self._send(self.topics.device("DBIRTH"), metrics)
            self._told = values
            self.births += 1

    async def _update(self, snapshot: dict[str, Any] | None = None) -> None:
        """DDATA of the metrics that changed since the host was last told, if any."""
        if self._client is None:
            return
        async with self._lock:
            values = self._sample(snapshot)
            changed = sp.changed_metrics(self._told, values, now_ms())
            if changed:
                await self._send(self.topics.device("DDATA"), changed)
                self._told = values

    async def _feed(self, subscription: Any) -> None:
        while True:
            try:
                message = await subscription.get()
            except SubscriptionClosed:
                subscription = self.cell.bus.subscribe(BUS_BUFFER, types=("state_changed",))
                await self._guarded(self._update())
                continue
            journal = self.cell.journal
            if journal is not None:
                await journal.caught_up()  # published after its commit, as the MQTT link
            await after_answers(self._answers)
            await self._guarded(self._update(message.data["snapshot"]))

    def _run_ended(self, ended: RunEnded) -> None:
        """In the worker: only starts a task that reads the KPIs again (counts, OEE)."""
        task = asyncio.get_running_loop().create_task(self._refresh_kpis(), name="sparkplug-kpis")
        self._in_flight.add(task)
        task.add_done_callback(self._in_flight.discard)

    async def _refresh_kpis(self) -> None:
        try:
            self._kpi_values = await self._kpis()
        except Exception as exc:  # a journal read failed: the next look tries again
            log.warning("Sparkplug B: KPIs not read: %s", exc)
            return
        await self._guarded(self._update())

    async def _ticker(self) -> None:
        next_kpis = 0.0
        while True:
            if time.monotonic() >= next_kpis:
                next_kpis = time.monotonic() + self.settings.mqtt_kpis_interval
                await self._refresh_kpis()
            else:
                await self._guarded(self._update())
            await asyncio.sleep(TICK_S)

    async def _guarded(self, work: Awaitable[None]) -> None:
        """A publish that failed with the connection: the connection task reconnects."""
        with contextlib.suppress(aiomqtt.MqttError):
            await work

    # --- the connection ------------------------------------------------------------------

    def _client_for(self) -> aiomqtt.Client:
        settings = self.settings
        tls_context = None
        if self.tls:
            tls_context = ssl.create_default_context(
                cafile=str(settings.mqtt_ca_file) if settings.mqtt_ca_file else None
            )
        password = settings.mqtt_password.get_secret_value() if settings.mqtt_password else None
        death = encode(Payload(now_ms(), (sp.bd_seq_metric(self._bd_seq, now_ms()),)))
        return aiomqtt.Client(
            self.host,
            self.port,
            username=settings.mqtt_username,
            password=password,
            identifier=f"glue-cell-{settings.cell_id}-sparkplug",
            protocol=aiomqtt.ProtocolVersion.V311,
            clean_session=True,
            will=aiomqtt.Will(self.topics.node("NDEATH"), death, qos=1, retain=False),
            keepalive=settings.mqtt_keepalive,
            tls_context=tls_context,
            timeout=max(10.0, 2.0 * settings.mqtt_keepalive),
        )

    def _take_bd_seq(self) -> None:
        """This connection's bdSeq: the one kept on disk (0 if none), the next one written
        back before the connection is made, so no two sessions share one."""
        # None yet, or unreadable: go on from the one in memory.
        with contextlib.suppress(OSError, ValueError):
            self._bd_seq = int(self._bd_seq_file.read_text().strip()) % sp.SEQ_LIMIT
        try:
            self._bd_seq_file.write_text(f"{(self._bd_seq + 1) % sp.SEQ_LIMIT}\n")
        except OSError as exc:
            log.warning("Sparkplug B: cannot keep the next bdSeq in %s: %s", self._bd_seq_file, exc)

    async def _connection(self) -> None:
        backoff = FIRST_BACKOFF_S
        first = True
        while True:
            self._take_bd_seq()
            try:
                async with self._client_for() as client:
                    await client.subscribe(self.topics.node("NCMD"), qos=1)
                    await client.subscribe(self.topics.device("DCMD", "+"), qos=1)
                    self._client = client
                    log.log(
                        logging.INFO if first else logging.WARNING,
                        "Sparkplug B: connected to %s:%d (bdSeq %d)",
                        self.host,
                        self.port,
                        self._bd_seq,
                    )
                    first = False
                    backoff = FIRST_BACKOFF_S
                    await self._birth()
                    await self._listen(client)
            except (aiomqtt.MqttError, OSError) as exc:  # OSError: TLS or socket, before MQTT
                self._down(str(exc))
            finally:
                self._client = None
            if self._stopping:
                return
            self._bd_seq = (self._bd_seq + 1) % sp.SEQ_LIMIT  # if the file is not there
            await asyncio.sleep(backoff * random.uniform(0.8, 1.2))
            backoff = min(2 * backoff, self.settings.mqtt_reconnect_max)

    def _down(self, error: str) -> None:
        """Say a lost connection, and an unreachable broker once per distinct error."""
        if self._client is not None:
            log.warning("Sparkplug B: lost %s:%d: %s", self.host, self.port, error)
        elif error != self._last_error:
            log.warning("Sparkplug B: cannot reach %s:%d: %s", self.host, self.port, error)
        self._last_error = error

    async def _listen(self, client: aiomqtt.Client) -> None:
        async for message in client.messages:
            topic = str(message.topic)
            raw = message.payload if isinstance(message.payload, bytes) else b""
            try:
                payload = decode(raw)
            except PayloadError as exc:
                log.warning("Sparkplug B: %s is not a Sparkplug B payload: %s", topic, exc)
                continue
            if topic == self.topics.node("NCMD"):
                if sp.rebirth_requested(payload.metrics):
                    log.info("Sparkplug B: rebirth requested")
                    await self._birth()
            elif topic == self.topics.device("DCMD"):
                for name, command in sp.commands_in(payload.metrics):
                    task = asyncio.create_task(
                        self._command(topic, name, command, payload.timestamp),
                        name="sparkplug-command",
                    )
                    self._in_flight.add(task)
                    task.add_done_callback(self._in_flight.discard)

    async def _command(self, topic: str, name: str, command: Command, sent_ms: int) -> None:
        """One DCMD command, through the command door as the configured token; its answer
        goes to the host as `Command/Last/...`."""
        action = f"Sparkplug {topic} {name}"
        door = self._door
        token_id = self.settings.sparkplug_command_token_id
        if door is None or token_id is None:
            log.info("Sparkplug B: %s ignored: commands are off (sparkplug_command_token_id)", name)
            return
        found = self._tokens.mqtt_key(token_id)
        age_ms = now_ms() - sent_ms
        if found is None:
            status, body = door.refuse(
                None, action, 401, "the Sparkplug command token is unknown or revoked"
            )
        elif age_ms > self.settings.mqtt_command_max_age * 1000:
            status, body = door.refuse(
                found[1],
                action,
                401,
                f"stale: sent {age_ms / 1000:.1f} s ago, more than "
                f"{self.settings.mqtt_command_max_age:g} s (mqtt_command_max_age)",
            )
        else:
            status, body = await door.execute(found[1], action, command, {})
        self._last = {
            sp.LAST_NAME: name,
            sp.LAST_STATUS: status,
            sp.LAST_MESSAGE: str(body.get("message") or body.get("detail") or ""),
        }
        await self._guarded(self._update())
