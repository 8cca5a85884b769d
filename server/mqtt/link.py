"""The link to the plant's MQTT broker: one more bus subscriber, never waited on.

Three tasks, none of which the worker or the e-stop ever awaits:

- the feed reads the bus (its own bounded subscription, like a WebSocket
  client) and turns each record into topic messages in the outbox at once, so
  a transition is on its way to the broker within a turn of the event loop; a
  run's progress goes at most every `plant_progress_interval`, the latest kept
  (server/core/infra/paced_feed.py);
- the connection publishes the outbox in order at QoS 1 while the broker is
  there, and reconnects with a doubling backoff (capped at
  `mqtt_reconnect_max`) while it is not; the outbox bounds what waits
  (server/mqtt/outbox.py: the oldest event, progress and alert messages are
  dropped and counted, the retained topics keep their latest);
- the ticker republishes the retained health when it changes and every
  `mqtt_health_interval`, and the KPIs every `mqtt_kpis_interval` and within a
  tick after each run ends (a part's count is not a period late).

The broker is told `online` on `status` at each connection, with its time, and
a last will of `offline` it publishes itself if the cell goes silent for 1.5
keep-alives (a killed server, a cut cable); a clean stop says `offline` with its
time before it leaves (server/mqtt/topics.py: `status_message`). Progress of a
run that ended while the broker was away is not sent when it is back.
Commands (server/mqtt/commands.py) each get a task of their own, so an e-stop
never waits behind a command still being decided.

The stop has a lane of its own, as over HTTP (server/api/stop_lane.py). Commands
wait in two queues before the link decides them: the broker's, which delivers
a connection's messages in order and only so many unacknowledged at a time,
and the client's incoming queue, which the listener empties one message per
turn of the loop, each command's check and answer beside it. A stop behind
thousands of commands waited for all of them. So:

- a second connection, the stop lane (client id `glue-cell-<id>-stops`, no
  will), subscribes to the stop commands' topics alone (the catalogue's `stop`
  entries): the broker delivers a stop to it whatever waits for the first
  connection, which leaves those topics to the lane while it is up (and serves
  them itself while it is not);
- on both connections the incoming queue is the link's own (`StopFirstQueue`):
  as the client parses a stop off the socket, it is taken out of the line and
  its task started there and then, first step run
  (server/core/infra/eager.py: `start_task`). Its signature, freshness and role
  are checked exactly as any command's, and the devices' halt frames are
  written before the client parses the next message.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import random
import ssl
import time
import weakref
from collections import deque
from collections.abc import Awaitable, Callable
from typing import Any
from urllib.parse import urlsplit

import aiomqtt
from aiomqtt import Message
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from server.bootstrap.cell import Cell
from server.commands.catalogue import ADMITTED, STOP_COMMANDS, is_stop
from server.core.infra.answers_in_flight import AnswersInFlight, after_answers
from server.core.infra.bus import SubscriptionClosed
from server.core.infra.eager import start_task
from server.core.infra.paced_feed import PacedFeed
from server.core.machine.transitions import normalize_command
from server.core.worker.runs import RunEnded
from server.mqtt.commands import CommandDoor
from server.mqtt.outbox import Entry, Outbox
from server.mqtt.publishing import publish_outbox
from server.mqtt.topics import (
    Topics,
    alert_message,
    encode,
    event_message,
    progress_message,
    run_message,
    state_message,
    status_message,
)
from server.settings.mqtt import MqttSettings
from server.settings.plant import PlantSettings

log = logging.getLogger(__name__)

BUS_TYPES = ("state_changed", "progress", "alert", "error", "report")
BUS_BUFFER = 1024  # records between the bus and the outbox: drained at once, so rarely used
FIRST_BACKOFF_S = 0.1
STOP_FLUSH_S = 2.0  # at a clean stop, how long `offline` (and what waits) may take to go
TICK_S = 1.0  # how often the health is looked at for a change
MAX_COMMANDS_WAITING = 64  # more than this in the incoming queue: refused (503), never a stop


def broker_address(url: str) -> tuple[str, int, bool]:
    """Host, port and whether TLS, from mqtt://host[:port] or mqtts://host[:port]."""
    parts = urlsplit(url)
    tls = parts.scheme == "mqtts"
    return parts.hostname or "", parts.port or (8883 if tls else 1883), tls


def _health_signature(health: dict[str, Any]) -> str:
    """What a change of health means: status, state, each device's link and faults, the
    journal's failure; not the figures that move with every event (rtt, counts)."""
    devices = {
        name: (device.get("connected"), device.get("active_faults"))
        for name, device in health.get("devices", {}).items()
    }
    journal = health.get("journal", {})
    mqtt = health.get("mqtt", {})
    key = [health.get("status"), health.get("state"), devices, journal.get("last_error")]
    return json.dumps([*key, mqtt.get("dropped")], sort_keys=True, default=str)


class StopFirstQueue(asyncio.Queue[Message]):
    """The client's incoming queue, with the stop commands taken out as they arrive.

    aiomqtt puts each message here from its socket reader (in the loop's thread, a
    message at a time, as the client parses it). `divert` is asked first: a message it
    takes (a stop) never enters the queue, so it waits behind nothing the listener has
    still to read.
    """

    def __init__(self, divert: Callable[[Message], bool], maxsize: int = 0) -> None:
        super().__init__(maxsize)
        self._divert = divert

    def put_nowait(self, item: Message) -> None:
        if not self._divert(item):
            super().put_nowait(item)


class MqttLink:
    """Publishes the cell to a broker and, if enabled, takes commands from it."""

    def __init__(
        self,
        settings: MqttSettings,
        plant: PlantSettings,
        cell: Cell,
        *,
        health: Callable[[], dict[str, Any]],
        kpis: Callable[[], Awaitable[dict[str, Any]]],
        commands: CommandDoor | None = None,
        answers: AnswersInFlight | None = None,
    ) -> None:
        assert settings.mqtt_url is not None
        self.settings = settings
        self.plant = plant
        self.cell = cell
        self.host, self.port, self.tls = broker_address(settings.mqtt_url)
        self.topics = Topics(settings.mqtt_topic_prefix, plant.cell_id)
        self.outbox = Outbox(settings.mqtt_buffer)
        self._health = health
        self._kpis = kpis
        self._commands = commands
        self._answers = answers  # the commands being answered, which go first
        self._client: aiomqtt.Client | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._in_flight: set[asyncio.Task[None]] = set()
        self._admitted = asyncio.Semaphore(ADMITTED)  # commands (not stops) served at once
        # the e-stops counted as each command message was read off the socket
        self._asked: weakref.WeakKeyDictionary[Message, int] = weakref.WeakKeyDictionary()
        self._connected = False
        self._since: float | None = None
        self._reconnects = 0
        self._last_error: str | None = None
        self._dropped_at_loss = 0
        self._stopping = False
        self._drained = asyncio.Event()  # set when the outbox was published to the end
        self._held_runs: deque[tuple[int, Entry]] = deque()  # run messages waiting for a seq
        self._handled_seq = 0  # the last bus record the feed put in the outbox
        self._online_at: float | None = None  # when the present connection was made
        self._lane_topics = frozenset(
            f"{self.topics.base}/command/{command.value}" for command in STOP_COMMANDS
        )
        self._lane_client: aiomqtt.Client | None = None
        self._lane_up = False  # subscribed to every stop topic

    # --- life ----------------------------------------------------------------

    def start(self) -> None:
        """Subscribe to the bus and start connecting; returns at once."""
        subscription = self.cell.bus.subscribe(BUS_BUFFER, types=BUS_TYPES)
        self._put_state()  # the present first, then every later change from the bus
        self.cell.view.on_run_ended(self._run_ended)
        paced = PacedFeed(subscription, self.plant.plant_progress_interval)
        self._tasks = [
            asyncio.create_task(self._feed(paced), name="mqtt-feed"),
            asyncio.create_task(self._connection(), name="mqtt-connection"),
            asyncio.create_task(self._ticker(), name="mqtt-ticker"),
        ]
        if self._commands is not None:
            self._tasks.append(asyncio.create_task(self._stop_lane(), name="mqtt-stop-lane"))
        log.info(
            "MQTT: publishing to %s:%d under %s/ (commands %s)",
            self.host,
            self.port,
            self.topics.base,
            "on" if self._commands else "off",
        )

    async def stop(self) -> None:
        """Say `offline` (retained) if the broker is there, then leave cleanly."""
        self._stopping = True
        feed, connection, ticker, *lane = self._tasks or (None, None, None)
        for task in (feed, ticker, *lane, *self._in_flight):
            if task is not None:
                task.cancel()
        self._drained.clear()
        self._release_runs(self.cell.bus.last_seq)  # a run that ended last still goes out
        offline = status_message(
            self.topics.cell_id, "offline", time.time(), clean=True, online_since=None
        )
        self.outbox.put(Entry(self.topics.status, offline, retain=True))
        if connection is not None:
            if self._connected:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._drained.wait(), STOP_FLUSH_S)
            connection.cancel()
        await asyncio.gather(*self._tasks, *self._in_flight, return_exceptions=True)
        self._tasks = []

    def health(self) -> dict[str, Any]:
        """The link as /health shows it (`mqtt`)."""
        return {
            "connected": self._connected,
            "broker": f"{self.host}:{self.port}",
            "since": self._since,
            "buffered": len(self.outbox),
            "dropped": self.outbox.dropped,
            "reconnects": self._reconnects,
            "last_error": self._last_error,
            "commands": self._commands is not None,
        }

    # --- from the bus to the outbox -----------------------------------------------

    async def _feed(self, feed: PacedFeed) -> None:
        cell_id = self.topics.cell_id
        while True:
            try:
                message = await feed.get()
            except SubscriptionClosed as closed:
                log.warning("MQTT: the bus feed was closed (%s); the state is sent again", closed)
                feed.resubscribe(self.cell.bus.subscribe(BUS_BUFFER, types=BUS_TYPES))
                self._handled_seq = self.cell.bus.last_seq
                self._release_runs(self._handled_seq)
                self._put_state()
                continue
            data = message.data
            if message.type == "state_changed":
                await self._after_its_commit()
            await after_answers(self._answers)
            self._release_runs(message.seq - 1)  # a run that ended before this record
            if message.type == "state_changed":
                self._put_state(data)
                event = event_message(cell_id, message.seq, data)
                self.outbox.put(Entry(self.topics.event, encode(event)))
                self._put_health_if_changed()
            elif message.type == "progress":
                progress = progress_message(cell_id, data)
                if progress is not None and not self._stale(progress["run_id"]):
                    entry = Entry(self.topics.progress, encode(progress), run_id=progress["run_id"])
                    self.outbox.put(entry)
            elif message.type == "report":  # a shift's or a day's, retained: the latest
                report = {"cell_id": cell_id, **data}
                self.outbox.put(Entry(self.topics.report, encode(report), retain=True))
            else:  # alert (a warning) or error (a fault)
                alert = alert_message(cell_id, message.type, message.time, data)
                self.outbox.put(Entry(self.topics.alert, encode(alert)))
            self._handled_seq = message.seq
            self._release_runs(message.seq)

    def _current_run_id(self) -> str | None:
        run = self.cell.view.current_run()
        return run.get("run_id") if run else None

    def _stale(self, run_id: str | None) -> bool:
        """Progress of a run that has ended, while the broker is away: it would arrive
        after the run's end, so it is not queued (when connected it goes as it is, just
        behind the run's own messages, as the pacing already orders them)."""
        return not self._connected and run_id is not None and run_id != self._current_run_id()

    def _run_ended(self, ended: RunEnded) -> None:
        """In the worker: only queues. The run's message waits until the feed has put the
        records published before it (by bus seq) in the outbox, and goes before the
        transition that follows the run's end: so a subscriber hears the run, then the
        cell leaving its state, in the order they happened (as the webhooks do)."""
        message = run_message(self.topics.cell_id, ended, time.time())
        self._kpis_due = True  # the part's count: at the ticker's next look, as Sparkplug B
        self._held_runs.append((self.cell.bus.last_seq, Entry(self.topics.run, encode(message))))
        if self._handled_seq >= self.cell.bus.last_seq:  # the feed is idle: nothing before it
            self._release_runs(self._handled_seq)

    def _release_runs(self, through_seq: int) -> None:
        while self._held_runs and self._held_runs[0][0] <= through_seq:
            self.outbox.put(self._held_runs.popleft()[1])

    async def _after_its_commit(self) -> None:
        """Wait until the transition's records are committed before publishing it.

        Why: the publishing (the state, the event, a fresh health document) is CPU
        work on the loop and under the interpreter lock, and the command that made
        the transition (an e-stop above all) is answered only once its commit is
        done; the journal's writer thread needs the lock to get there. Published
        after the commit, the plant hears of a transition about a millisecond
        later. The commit alone was not enough (the answer is written a few turns
        of the loop after it): every message then also waits until no command's
        answer is in flight (server/core/infra/answers_in_flight.py).
        """
        journal = self.cell.journal
        if journal is not None:
            await journal.caught_up()

    def _put_state(self, changed: dict[str, Any] | None = None) -> None:
        """The retained state: of the transition `changed` records, else the present one.

        A run starts just after its transition is published, in the same turn of
        the worker, so the run is read from the view while the view is still in
        that state (same since); otherwise the transition's own snapshot has it.
        """
        view = self.cell.view
        snapshot = changed["snapshot"] if changed else view.snapshot()
        run = view.current_run() if view.since == snapshot["since"] else None
        state = state_message(self.topics.cell_id, snapshot, run)
        self.outbox.put(Entry(self.topics.state, encode(state), retain=True))

    _last_health = ""
    _kpis_due = False  # a run ended since the KPIs were last published

    def _put_health_if_changed(self, *, anyway: bool = False) -> None:
        health = self._health()
        signature = _health_signature(health)
        if anyway or signature != self._last_health:
            self._last_health = signature
            payload = encode({"cell_id": self.topics.cell_id, **health})
            self.outbox.put(Entry(self.topics.health, payload, retain=True))

    async def _ticker(self) -> None:
        settings = self.settings
        next_health = next_kpis = 0.0
        while True:
            now = time.monotonic()
            self._put_health_if_changed(anyway=now >= next_health)
            if now >= next_health:
                next_health = now + settings.mqtt_health_interval
            if now >= next_kpis or self._kpis_due:
                next_kpis = now + settings.mqtt_kpis_interval
                self._kpis_due = False
                try:
                    kpis = await self._kpis()
                except Exception as exc:  # a journal read failed: the next tick tries again
                    log.warning("MQTT: KPIs not published: %s", exc)
                else:
                    payload = encode({"cell_id": self.topics.cell_id, **kpis})
                    self.outbox.put(Entry(self.topics.kpis, payload, retain=True))
            await asyncio.sleep(TICK_S)

    # --- the connection ------------------------------------------------------------

    def _client_for(self, *, lane: bool = False) -> aiomqtt.Client:
        settings = self.settings
        tls_context = None
        if self.tls:
            tls_context = ssl.create_default_context(
                cafile=str(settings.mqtt_ca_file) if settings.mqtt_ca_file else None
            )
        password = settings.mqtt_password.get_secret_value() if settings.mqtt_password else None
        return aiomqtt.Client(
            self.host,
            self.port,
            username=settings.mqtt_username,
            password=password,
            identifier=f"glue-cell-{self.plant.cell_id}{'-stops' if lane else ''}",
            protocol=aiomqtt.ProtocolVersion.V5,
            will=None
            if lane
            else aiomqtt.Will(self.topics.status, self._will(), qos=1, retain=True),
            keepalive=settings.mqtt_keepalive,
            tls_context=tls_context,
            timeout=max(10.0, 2.0 * settings.mqtt_keepalive),
            queue_type=self._queue_type(lane),
        )

    def _will(self) -> bytes:
        """`offline` for the broker to publish if the cell falls silent: no time (it is
        written now, published later); `online_since` names the connection it ends."""
        self._online_at = time.time()
        return status_message(
            self.topics.cell_id, "offline", None, clean=False, online_since=self._online_at
        )

    def _queue_type(self, lane: bool) -> type[asyncio.Queue[Message]]:
        """The incoming queue's class for aiomqtt, which makes it with `maxsize` alone."""

        def divert(message: Message) -> bool:
            return self._stop_at_once(message, lane)

        class Incoming(StopFirstQueue):
            def __init__(self, maxsize: int = 0) -> None:
                super().__init__(divert, maxsize)

        return Incoming

    def _stop_at_once(self, message: Message, lane: bool) -> bool:
        """A stop command: its task started now, first step run (its check and the halt
        frames written), or left to the stop lane when it is up and has it; True.
        Anything else: False, for the queue."""
        if self._commands is None or self._stopping:
            return False
        topic = str(message.topic)
        name = self.topics.command_name(topic)
        if name is None or not is_stop(normalize_command(name)):
            # refused if a stop comes ahead of it (server/core/machine/decide.py)
            self._asked[message] = self.cell.stops_now()
            return False
        if not lane and self._lane_up and topic in self._lane_topics:
            return True  # the lane's subscription has it too: served there
        client = self._lane_client if lane else self._client
        task = start_task(self._command(message, topic, name, client))
        self._in_flight.add(task)
        task.add_done_callback(self._in_flight.discard)
        return True

    async def _connection(self) -> None:
        backoff = FIRST_BACKOFF_S
        first = True
        while True:
            try:
                async with self._client_for() as client:
                    self._up(client, first)
                    first = False
                    backoff = FIRST_BACKOFF_S
                    online = status_message(
                        self.topics.cell_id,
                        "online",
                        self._online_at,
                        clean=True,
                        online_since=None,
                    )
                    await client.publish(self.topics.status, online, qos=1, retain=True)
                    if self._commands is not None:
                        await client.subscribe(self.topics.commands, qos=1)
                    async with asyncio.TaskGroup() as group:
                        group.create_task(self._publish(client))
                        group.create_task(self._listen(client))
            except* aiomqtt.MqttError as errors:
                self._down(str(errors.exceptions[0]))
            except* OSError as errors:  # a TLS or socket failure before MQTT spoke
                self._down(str(errors.exceptions[0]))
            if self._stopping:
                return
            await asyncio.sleep(backoff * random.uniform(0.8, 1.2))
            backoff = min(2 * backoff, self.settings.mqtt_reconnect_max)

    async def _stop_lane(self) -> None:
        """The stop lane's connection: the stop topics alone, each stop served as it is
        parsed (`_stop_at_once`); its messages never reach the queue, which is read
        only to notice a lost connection. Reconnects as the first connection does."""
        backoff = FIRST_BACKOFF_S
        while True:
            try:
                async with self._client_for(lane=True) as client:
                    self._lane_client = client
                    backoff = FIRST_BACKOFF_S
                    for topic in self._lane_topics:
                        await client.subscribe(topic, qos=1)
                    self._lane_up = True
                    async for _ in client.messages:
                        pass
            except (aiomqtt.MqttError, OSError) as error:
                if self._lane_up:
                    log.warning("MQTT: the stop lane lost %s:%d: %s", self.host, self.port, error)
            finally:
                self._lane_up = False
                self._lane_client = None
            if self._stopping:
                return
            await asyncio.sleep(backoff * random.uniform(0.8, 1.2))
            backoff = min(2 * backoff, self.settings.mqtt_reconnect_max)

    def _up(self, client: aiomqtt.Client, first: bool) -> None:
        self._client = client
        self._connected = True
        self._since = time.time()
        if first:
            log.info("MQTT: connected to %s:%d", self.host, self.port)
            return
        self._reconnects += 1
        stale = self.outbox.discard_progress(self._current_run_id())
        if stale:
            log.info("MQTT: %d progress messages of runs that have ended are not sent", stale)
        dropped = self.outbox.dropped - self._dropped_at_loss
        log.warning(
            "MQTT: connected to %s:%d again; %d messages waiting are sent now, %d were "
            "dropped while it was away (%d since start)",
            self.host,
            self.port,
            len(self.outbox),
            dropped,
            self.outbox.dropped,
        )

    def _down(self, error: str) -> None:
        if self._connected:
            log.warning("MQTT: lost %s:%d: %s", self.host, self.port, error)
            self._since = time.time()
            self._dropped_at_loss = self.outbox.dropped
        elif error != self._last_error:
            log.warning("MQTT: cannot reach %s:%d: %s", self.host, self.port, error)
        self._connected = False
        self._client = None
        self._last_error = error

    async def _publish(self, client: aiomqtt.Client) -> None:
        """The outbox, in order, each message acknowledged (`publishing.py`)."""
        await publish_outbox(client, self.outbox, self._drained)

    async def _listen(self, client: aiomqtt.Client) -> None:
        """Commands, each in a task of its own, at most ADMITTED at once; also how a lost
        connection is noticed.

        Why a few at a time: each command's check (a signature), submission and answer
        is work on the loop, and a flood's commands started together made turns of the
        loop long enough to hold back the stop lane's socket (docs/benchmarks.md, "The
        stop through every door"). The commands beyond them wait in the client's
        incoming queue, as parsed messages, not tasks; more than MAX_COMMANDS_WAITING
        there and the one read is refused (503). A stop never waits for a slot.
        """
        async for message in client.messages:
            if self._commands is None:
                continue
            topic = str(message.topic)
            name = self.topics.command_name(topic)
            if name is None:
                continue
            if not is_stop(normalize_command(name)):
                if len(client.messages) >= MAX_COMMANDS_WAITING:
                    answer = (503, {"accepted": False, "message": "too many MQTT commands at once"})
                    await self._answer(message, answer, client)
                    continue
                await self._admitted.acquire()
                command = self._command(message, topic, name, client)
                task = asyncio.create_task(command, name="mqtt-command")
                task.add_done_callback(lambda _: self._admitted.release())
            else:
                task = asyncio.create_task(self._command(message, topic, name, client))
            self._in_flight.add(task)
            task.add_done_callback(self._in_flight.discard)

    async def _command(
        self, message: aiomqtt.Message, topic: str, name: str, client: aiomqtt.Client | None
    ) -> None:
        assert self._commands is not None
        raw = message.payload if isinstance(message.payload, bytes) else b""
        answer = await self._commands.handle(topic, name, raw, self._asked.pop(message, None))
        await self._answer(message, answer, client)

    async def _answer(
        self,
        message: aiomqtt.Message,
        answer: tuple[int, dict[str, Any]],
        client: aiomqtt.Client | None,
    ) -> None:
        """On the request's v5 response topic, with its correlation data, by the connection
        it came on; none asked, none sent."""
        asked = message.properties
        response_topic = getattr(asked, "ResponseTopic", None) if asked else None
        if not response_topic or client is None:
            return
        properties = Properties(PacketTypes.PUBLISH)
        correlation = getattr(asked, "CorrelationData", None)
        if correlation is not None:
            properties.CorrelationData = correlation
        properties.ContentType = "application/json"
        status, body = answer
        with contextlib.suppress(aiomqtt.MqttError):
            await client.publish(
                response_topic, encode({"status": status, **body}), qos=1, properties=properties
            )
