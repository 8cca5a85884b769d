"""Every command of the cell, declared once: the one table every transport serves.

An entry names the command (the operator's word, server/core/machine/transitions.py),
the event it posts, the role it needs, its request model and how the worker's payload
is built from it, its short OpenAPI operationId, its description, whether it is the
stop, and where it also appears: the OPC UA method (with the PackML command it stands
for) and the embedded façade's method. From here:

- HTTP routes are declared per entry (server/api/commands.py): path `/<name>`,
  operationId, summary and description;
- the access policy (server/security/policy.py) takes each command route's role;
- MQTT (server/mqtt/commands.py) accepts `command/<name>` for every entry;
- OPC UA (server/opcua/methods.py) adds a method for each entry that names one;
- gluectl and the Python client offer a command per entry, and the embedded façade
  a method per entry that names one (tests/unit/test_catalogue.py checks both);
- `may` answers "what may this principal do now": the commands its role allows,
  among those the state allows.

Adding a command is one entry here, its event in the transition table, and its
request model in server/commands/requests.py when it takes a body.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Final

from pydantic import BaseModel

from server.commands.requests import CreateWorkpieceRequest, EstopRequest, JogRequest, StartRequest
from server.core.machine.events import (
    CreateWorkpiecePayload,
    JogPayload,
    Payload,
    StartPayload,
    StopPayload,
)
from server.core.machine.transitions import COMMANDS, Command, Event
from server.security.tokens import Role


@dataclass(frozen=True)
class OpcuaMethod:
    """A command's OPC UA method: its browse name, the PackML command it stands for (None:
    the cell's own, PackML has none), its Description."""

    name: str
    packml: str | None
    description: str


@dataclass(frozen=True)
class CommandSpec:
    """One command as every transport serves it."""

    command: Command
    role: Role  # the least role that may send it
    operation_id: str  # OpenAPI's operationId: short, stable, camelCase
    summary: str  # OpenAPI's summary (the route's title)
    description: str  # what it does, for OpenAPI and the docs
    request: type[BaseModel] | None = None  # the body's model (None: it reads none)
    payload: Callable[[Any], Payload] | None = None  # the worker's payload from the body
    body_required: bool = False  # a body must be sent (else an empty one stands for defaults)
    stop: bool = False  # the software stop: halts the devices before it is queued
    opcua: OpcuaMethod | None = None
    facade: str | None = None  # the embedded façade's method (server/embedded/facade.py)

    @property
    def name(self) -> str:
        """The command's word: the HTTP path's, the MQTT topic's and gluectl's."""
        return self.command.value

    @property
    def event(self) -> Event:
        return COMMANDS[self.command]

    @property
    def path(self) -> str:
        """Its HTTP route (POST)."""
        return f"/{self.command.value}"


def start_payload(body: StartRequest | None) -> StartPayload:
    body = body or StartRequest()
    return StartPayload(body.contour_matching, body.workpiece_id)


def create_workpiece_payload(body: CreateWorkpieceRequest | None) -> CreateWorkpiecePayload:
    body = body or CreateWorkpieceRequest()
    spray = body.spray.model_dump(exclude_none=True) if body.spray is not None else None
    return CreateWorkpiecePayload(body.name, body.workpiece_id, spray, body.if_new)


def estop_payload(body: EstopRequest | None) -> StopPayload:
    return StopPayload(body.reason if body else None)


def jog_payload(body: JogRequest) -> JogPayload:
    return JogPayload(body.axis, body.distance_mm)


VIEW, OPER, MAINT = Role.VIEWER, Role.OPERATOR, Role.MAINTENANCE

CATALOGUE: Final = (
    CommandSpec(
        Command.START,
        OPER,
        "start",
        "Start",
        "Start spraying (IDLE → EXECUTING_TRAJECTORY).",
        request=StartRequest,
        payload=start_payload,
        opcua=OpcuaMethod(
            "Start",
            "Start",
            "spray: WorkpieceId names a library part (empty: find the part on the table)",
        ),
        facade="start",
    ),
    CommandSpec(
        Command.CALIBRATE_ROBOT,
        MAINT,
        "calibrateRobot",
        "Calibrate Robot",
        "Calibrate camera → robot coordinates from the ArUco markers (IDLE → CALIBRATING_ROBOT).",
        facade="calibrateRobot",
    ),
    CommandSpec(
        Command.CALIBRATE_CAMERA,
        MAINT,
        "calibrateCamera",
        "Calibrate Camera",
        "Calibrate the camera's intrinsics (IDLE → CALIBRATING_CAMERA).",
        facade="calibrateCamera",
    ),
    CommandSpec(
        Command.CREATE_WORKPIECE,
        OPER,
        "createWorkpiece",
        "Create Workpiece",
        "Capture the part on the table into the library (IDLE → CREATING_WORKPIECE).",
        request=CreateWorkpieceRequest,
        payload=create_workpiece_payload,
        facade="createWorkpiece",
    ),
    CommandSpec(
        Command.PAUSE,
        OPER,
        "pause",
        "Pause",
        "Stop the trajectory where it is: valve closed and robot still before PAUSED is answered.",
        opcua=OpcuaMethod("Pause", "Hold", "hold the run: valve closed, robot still"),
        facade="pause",
    ),
    CommandSpec(
        Command.RESUME,
        OPER,
        "resume",
        "Resume",
        "Continue a paused trajectory: back to where the robot stopped, then the same segment.",
        opcua=OpcuaMethod("Resume", "Unhold", "continue the held run"),
        facade="resume",
    ),
    CommandSpec(
        Command.CANCEL,
        OPER,
        "cancel",
        "Cancel",
        "Stop the running operation at once, glue off, and return to IDLE.",
        opcua=OpcuaMethod("Cancel", "Stop", "end the operation, glue off, to IDLE"),
        facade="cancel",
    ),
    CommandSpec(
        Command.ESTOP,
        VIEW,  # open to every signed-in role: nobody must be unable to stop the cell
        "estop",
        "Estop",
        "Software stop: valve closed and robot stopped at once, then ERROR.\n\n"
        "A supervisory stop, not a safety function: the hard-wired e-stop circuit\n"
        "remains the cell's safety stop.",
        request=EstopRequest,
        payload=estop_payload,
        stop=True,
        opcua=OpcuaMethod(
            "EmergencyStop",
            "Abort",
            "software stop: valve closed and robot stopped at once, then ERROR",
        ),
        facade="emergency_stop",
    ),
    CommandSpec(
        Command.RESET,
        MAINT,
        "reset",
        "Reset",
        "Leave ERROR for IDLE, once every device answers again; never restarts an operation.",
        opcua=OpcuaMethod("Reset", "Reset", "leave ERROR once every device answers"),
        facade="reset",
    ),
    CommandSpec(
        Command.HOME,
        MAINT,
        "home",
        "Home",
        "Send the robot to its safe position (IDLE, stays IDLE; target checked first).\n\n"
        "The only way the robot moves outside an operation: nothing else (a reset,\n"
        "a restart, the end of a run) moves it by itself.",
    ),
    CommandSpec(
        Command.JOG,
        MAINT,
        "jog",
        "Jog",
        "Move the robot one bounded step along one axis, at jog speed (IDLE, stays IDLE).\n\n"
        "For maintenance teaching marker positions. Refused unless IDLE (409); a step\n"
        "longer than jog_max_step_mm or a target outside the workspace is a 422 naming\n"
        "`distance_mm`, checked against the pose the worker reads before anything moves.\n"
        "Answered once the step has begun, like home; the e-stop or a fault stops it.",
        request=JogRequest,
        payload=jog_payload,
        body_required=True,
    ),
    CommandSpec(
        Command.PURGE,
        MAINT,  # the arm moves and glue flows outside a run: the role that may home and jog
        "purge",
        "Purge",
        "Purge the glue line (IDLE, stays IDLE): the nozzle to purge_position (checked\n"
        "against the workspace first), then the valve open for purge_seconds at\n"
        "purge_flow_ml_min into the purge cup. Restarts the pot life. Answered once it\n"
        "has begun, like home; the e-stop or a fault stops it with the valve closed.",
        opcua=OpcuaMethod(
            "Purge",
            None,  # no PackML command purges; it is a maintenance task of the cell's own
            "purge the glue line at purge_position (IDLE, stays IDLE); restarts the pot life",
        ),
    ),
)

BY_COMMAND: Final = MappingProxyType({spec.command: spec for spec in CATALOGUE})
# The stop routes on HTTP (POST): made in the stop lane just inside the gate, never
# locked out, never refused over their body (server/api/stop_lane.py).
STOP_PATHS: Final = tuple(spec.path for spec in CATALOGUE if spec.stop)
# The stop commands, which every door serves ahead of its own queue: HTTP's stop lane,
# MQTT's stop topics (server/mqtt/link.py), OPC UA's stop methods (server/opcua/).
STOP_COMMANDS: Final = frozenset(spec.command for spec in CATALOGUE if spec.stop)


# The HTTP command routes (POST) that are not stops: served at most ADMITTED at once.
COMMAND_PATHS: Final = frozenset(spec.path for spec in CATALOGUE if not spec.stop)
# Commands (not stops) each door serves at once, HTTP, MQTT and OPC UA alike; the rest wait
# as what they are (a request read, a message decoded, a call), not as tasks at work. Why:
# a door that starts a flood's commands all at once makes a turn of the loop as long as
# all their checks, and a stop read meanwhile waits for that turn to end.
ADMITTED: Final = 4


def is_stop(command: Command | None) -> bool:
    """Whether `command` is a stop (None, an unknown command: not one)."""
    return command in STOP_COMMANDS


def spec_of(command: Command) -> CommandSpec:
    """The catalogue's entry for `command`."""
    return BY_COMMAND[command]


def may_send(role: Role, command: Command) -> bool:
    """Whether a principal of `role` may send `command` (its state aside)."""
    return role >= BY_COMMAND[command].role


def may(role: Role, available: Iterable[str]) -> list[str]:
    """What a principal of `role` may do now: the commands available in the current
    state (the worker's `available_commands`) that its role allows, in their order.

    Every GET /state asks; the answers are few (a role and a state's commands), so
    each is worked out once and kept (at most MAY_KEPT of them)."""
    key = (role, tuple(available))
    found = _may.get(key)
    if found is None:
        if len(_may) >= MAY_KEPT:
            _may.clear()
        found = _may[key] = tuple(
            name
            for name in key[1]
            if (command := _command_named(name)) is not None and may_send(role, command)
        )
    return list(found)


MAY_KEPT = 256
_may: dict[tuple[Role, tuple[str, ...]], tuple[str, ...]] = {}


def _command_named(name: str) -> Command | None:
    try:
        return Command(name)
    except ValueError:
        return None
