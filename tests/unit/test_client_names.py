"""The Python client names the server's states and commands itself (it must not import
the server package, see clients/client/__init__.py): these tests keep the copies equal.
"""

from __future__ import annotations

import inspect

import pytest

from clients.client import COMMANDS, STATES, AsyncCellClient, CellClient, builders, normalize_state
from server.core.machine.transitions import COMMANDS as SERVER_COMMANDS
from server.core.machine.transitions import State
from server.security.policy import POLICY


def test_the_clients_states_are_the_servers_in_the_servers_order() -> None:
    assert tuple(state.value for state in State) == STATES
    for state in State:
        assert normalize_state(state.value.lower()) == state.value


def test_the_clients_commands_are_the_servers() -> None:
    assert sorted(COMMANDS) == sorted(SERVER_COMMANDS)


@pytest.mark.parametrize("client", [CellClient, AsyncCellClient])
@pytest.mark.parametrize("command", sorted(SERVER_COMMANDS))
def test_each_server_command_is_a_method_of_both_clients(client: type, command: str) -> None:
    method = getattr(client, command.replace("-", "_"), None)
    assert method is not None, f"{client.__name__} has no method for {command}"
    assert inspect.iscoroutinefunction(method) == (client is AsyncCellClient)


@pytest.mark.parametrize("command", sorted(SERVER_COMMANDS))
def test_each_command_posts_to_its_own_route(command: str) -> None:
    call = builders.command(command)
    assert (call.method, call.path, tuple(call.ok)) == ("POST", f"/{command}", (202,))
    assert (call.method, call.path) in POLICY  # a route the server has


def test_an_unknown_command_is_not_built() -> None:
    with pytest.raises(ValueError, match="unknown command"):
        builders.command("explode")
