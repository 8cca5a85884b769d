"""The plant interfaces the composition root builds: OPC UA, MQTT and the webhooks.

OPC UA and MQTT (when configured) are each a bus subscriber and a command source
on the cell's own command path (DESIGN.md, principle 10). They are built with the
HTTP app (`server/bootstrap/app.py: create_app`), from the app's token store and
its answers in flight, and the app's lifespan starts them once the cell is up and
stops them before it goes down: OPC UA first, then MQTT, stopped in the reverse
order. The webhooks (`webhooks_of`) only listen: started as soon as the cell is,
and stopped between the cell's work and its journal (`stop_cell`), so what they
abandon is on record.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any

from server.bootstrap.cell import Cell
from server.common.errors import ConfigurationError
from server.core.infra.answers_in_flight import AnswersInFlight
from server.notify.notifier import Notifier
from server.security.tokens import TokenStore
from server.settings.model import Settings
from server.settings.mqtt import MqttSettings
from server.settings.notifications import WebhookSettings
from server.settings.opcua import OpcUaSettings
from server.settings.plant import PlantSettings

if TYPE_CHECKING:
    from server.mqtt.link import MqttLink
    from server.mqtt.sparkplug.node import SparkplugNode
    from server.opcua.interface import OpcUaInterface

log = logging.getLogger(__name__)


class PlantLinks:
    """OPC UA, MQTT and Sparkplug B, each None when its setting (opcua_endpoint, mqtt_url,
    sparkplug_group) is unset."""

    def __init__(
        self,
        cell: Cell,
        tokens: TokenStore,
        answers: AnswersInFlight,
        *,
        health: Callable[[], dict[str, Any]],
        kpis: Callable[[], Awaitable[dict[str, Any]]],
    ) -> None:
        self.opcua = _opcua(cell, tokens, answers)
        self.mqtt = _mqtt(cell, tokens, answers, health, kpis)
        self.sparkplug = _sparkplug(cell, tokens, answers, health, kpis)

    async def start(self) -> None:
        """Serve OPC UA, then link MQTT; the cell is started already.

        A failure to serve OPC UA is logged as one line and raised, and the caller
        stops the cell again (`stop_cell`): the server does not start without an
        interface it was configured to offer.
        """
        if self.opcua is not None:
            try:
                await self.opcua.start()
            except BaseException as exc:
                if isinstance(exc, ConfigurationError):
                    log.critical("cannot start: %s", exc)
                with contextlib.suppress(Exception):
                    await self.opcua.stop()
                raise
        if self.mqtt is not None:
            self.mqtt.start()
        if self.sparkplug is not None:
            self.sparkplug.start()

    async def stop(self) -> None:
        """Sparkplug, then MQTT (NDEATH and `offline` go out before the cell stops), then
        OPC UA."""
        if self.sparkplug is not None:
            await self.sparkplug.stop()
        if self.mqtt is not None:
            await self.mqtt.stop()
        if self.opcua is not None:
            await self.opcua.stop()


def webhooks_of(cell: Cell) -> Notifier:
    """The webhooks (server/notify/): one more bus subscriber, never waited on.

    Built before the cell starts, from its settings' `WebhookSettings` and its bus;
    with no webhook configured it subscribes to nothing and starts no task. Start it
    with the started cell's view and journal (`Notifier.start`), stop it with
    `stop_cell`."""
    settings = cell.settings
    return Notifier(settings.section(WebhookSettings), settings.cell_id, cell.bus)


async def stop_cell(cell: Cell, webhooks: Notifier) -> None:
    """The cell's work, then the webhooks, then the cell's records.

    The order matters: the worker's last records still reach the webhooks, and
    what the webhooks abandon (queued or in flight) is journaled before the
    journal closes."""
    await cell.stop_running()
    await webhooks.stop()
    await cell.close_records()


def _opcua(cell: Cell, tokens: TokenStore, answers: AnswersInFlight) -> OpcUaInterface | None:
    """The OPC UA server (server/opcua), if `opcua_endpoint` is set."""
    if cell.settings.opcua_endpoint is None:
        return None
    from server.opcua.interface import OpcUaInterface  # asyncua is loaded only when asked for

    settings = cell.settings
    return OpcUaInterface(
        cell,
        tokens,
        settings.section(OpcUaSettings),
        settings.section(PlantSettings),
        settings.data_path,
        answers=answers,
    )


def _mqtt(
    cell: Cell,
    tokens: TokenStore,
    answers: AnswersInFlight,
    health: Callable[[], dict[str, Any]],
    kpis: Callable[[], Awaitable[dict[str, Any]]],
) -> MqttLink | None:
    """The MQTT link, when mqtt_url is set (docs/plant-integration.md)."""
    settings: Settings = cell.settings
    if settings.mqtt_url is None:
        return None
    # aiomqtt and paho are loaded only when asked for, as asyncua is for OPC UA.
    from server.mqtt.commands import CommandDoor
    from server.mqtt.link import MqttLink

    door = None
    if settings.mqtt_commands:
        door = CommandDoor(
            cell,
            tokens,
            f"mqtt:{settings.mqtt_url}",
            max_age_s=settings.mqtt_command_max_age,
            max_skew_s=settings.mqtt_command_max_skew,
        )
    return MqttLink(
        settings.section(MqttSettings),
        settings.section(PlantSettings),
        cell,
        health=health,
        kpis=kpis,
        commands=door,
        answers=answers,
    )


def _sparkplug(
    cell: Cell,
    tokens: TokenStore,
    answers: AnswersInFlight,
    health: Callable[[], dict[str, Any]],
    kpis: Callable[[], Awaitable[dict[str, Any]]],
) -> SparkplugNode | None:
    """The Sparkplug B edge node, when sparkplug_group is set (on mqtt_url's broker)."""
    from server.mqtt.commands import CommandDoor  # aiomqtt is loaded only when asked for
    from server.mqtt.sparkplug.node import SparkplugNode
    from server.opcua.packml import packml_state  # the PackML numbers OPC UA shows

    settings: Settings = cell.settings
    if settings.sparkplug_group is None or settings.mqtt_url is None:
        return None
    door = None
    if settings.sparkplug_command_token_id is not None:
        door = CommandDoor(cell, tokens, f"sparkplug:{settings.mqtt_url}", source="sparkplug")
    return SparkplugNode(
        settings,
        cell,
        packml_state=lambda state: int(packml_state(state)),
        health=health,
        kpis=kpis,
        tokens=tokens,
        door=door,
        answers=answers,
    )
