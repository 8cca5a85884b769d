"""The command catalogue is the one declaration every door serves.

Each command has one entry; the HTTP routes, the access policy, OPC UA's methods,
the embedded façade, gluectl and the Python client (which may not import the
server, so they keep their own copies) all name the catalogue's commands; every
OpenAPI operationId is short and unique, the commands' taken from the catalogue.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import typer

from clients.client import COMMANDS as CLIENT_COMMANDS
from clients.gluectl.cli import app as gluectl_app
from server.commands.catalogue import (
    BY_COMMAND,
    CATALOGUE,
    STOP_PATHS,
    CommandSpec,
    may,
    may_send,
)
from server.core.machine.transitions import COMMANDS, Command
from server.embedded.facade import EmbeddedCell
from server.opcua.methods import METHODS
from server.security.policy import POLICY, required_role
from server.security.tokens import Role

ROOT = Path(__file__).resolve().parents[2]
NAMES = [spec.name for spec in CATALOGUE]


def test_each_command_is_declared_once_with_its_own_event() -> None:
    assert sorted(NAMES) == sorted(command.value for command in Command)
    assert len(NAMES) == len(set(NAMES))
    for spec in CATALOGUE:
        assert spec.event is COMMANDS[spec.command]
        assert BY_COMMAND[spec.command] is spec


def test_only_the_estop_is_a_stop_and_every_role_may_send_it() -> None:
    assert STOP_PATHS == ("/estop",)
    assert BY_COMMAND[Command.ESTOP].role is Role.VIEWER


def test_a_command_with_a_body_builds_its_payload_and_one_without_reads_none() -> None:
    for spec in CATALOGUE:
        assert (spec.request is None) == (spec.payload is None), spec.name
        assert not spec.body_required or spec.request is not None, spec.name


@pytest.mark.parametrize("spec", CATALOGUE, ids=NAMES)
def test_the_policy_takes_each_command_routes_role_from_the_catalogue(spec: CommandSpec) -> None:
    assert required_role("POST", spec.path) is spec.role
    assert POLICY[("POST", spec.path)] is spec.role


def test_opcua_offers_a_method_for_each_entry_naming_one_with_its_role() -> None:
    named = [(spec.opcua.name, spec.command, spec.role) for spec in CATALOGUE if spec.opcua]
    assert [(m.name, m.command, m.role) for m in METHODS] == named


def test_the_facade_has_each_method_the_catalogue_names() -> None:
    for spec in CATALOGUE:
        if spec.facade is not None:
            assert callable(getattr(EmbeddedCell, spec.facade, None)), spec.facade


def test_gluectl_and_the_python_client_offer_every_command() -> None:
    cli = typer.main.get_command(gluectl_app)
    offered = set(cli.commands)  # type: ignore[attr-defined]
    assert set(NAMES) <= offered, sorted(set(NAMES) - offered)
    assert list(CLIENT_COMMANDS) == NAMES  # the same commands, in the catalogue's order


def test_operation_ids_are_short_unique_and_the_commands_come_from_the_catalogue() -> None:
    document = json.loads((ROOT / "openapi.json").read_text(encoding="utf-8"))
    ids = {
        (method, path): operation["operationId"]
        for path, item in document["paths"].items()
        for method, operation in item.items()
        if isinstance(operation, dict) and "operationId" in operation
    }
    values = list(ids.values())
    assert len(values) == len(set(values)), "operationIds must be unique"
    assert all(re.fullmatch(r"[a-z][A-Za-z0-9]*", value) for value in values), values
    for spec in CATALOGUE:
        assert ids[("post", spec.path)] == spec.operation_id


def test_may_is_what_the_state_allows_and_the_role_allows() -> None:
    available = ["start", "calibrate-robot", "estop", "not-a-command"]
    assert may(Role.VIEWER, available) == ["estop"]
    assert may(Role.OPERATOR, available) == ["start", "estop"]
    assert may(Role.ADMIN, available) == ["start", "calibrate-robot", "estop"]
    assert may_send(Role.MAINTENANCE, Command.JOG)
    assert not may_send(Role.OPERATOR, Command.JOG)


def test_the_api_docs_table_has_one_row_per_command() -> None:
    text = (ROOT / "docs" / "api.md").read_text(encoding="utf-8")
    table = text.split("## Commands", 1)[1].split("Answers:", 1)[0]
    rows = re.findall(r"^\| `POST /([a-z-]+)` \|", table, flags=re.MULTILINE)
    assert rows == NAMES, "docs/api.md's command table: one row per catalogue entry, in order"
