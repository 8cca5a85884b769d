"""One validation for every door: the pure steps MQTT and OPC UA share with HTTP.

`payload_of` checks a command's body with the HTTP route's model and builds the worker's
payload with the route's own function; `body_of` says which body an OPC UA method's
input arguments stand for. Only pure logic here: the doors themselves are tested over
real sockets in tests/integration/test_one_validation.py.
"""

from __future__ import annotations

import math

import pytest
from asyncua import ua

from server.commands.answers import invalid_request, payload_of
from server.core.machine.events import StartPayload, StopPayload
from server.core.machine.transitions import Command
from server.opcua.methods import METHODS, body_of

START = next(m for m in METHODS if m.name == "Start")
PAUSE = next(m for m in METHODS if m.name == "Pause")


@pytest.mark.parametrize(
    "value",
    ["../../etc/passwd", "evil\u202e\nname", "demo\x00", "a" * 65, math.nan, math.inf, 7, [1]],
)
def test_a_bad_workpiece_id_names_the_field_never_the_value(value: object) -> None:
    payload, problems = payload_of(
        Command.START, {"contour_matching": False, "workpiece_id": value}
    )
    assert payload is None
    assert [p["field"] for p in problems] == ["workpiece_id"]
    detail = invalid_request(problems)
    assert detail.startswith("invalid request: workpiece_id: ")
    if isinstance(value, str):
        assert value not in detail


def test_a_good_body_builds_the_routes_payload() -> None:
    assert payload_of(Command.START, None) == (StartPayload(), [])
    assert payload_of(Command.START, {"contour_matching": False, "workpiece_id": "demo"}) == (
        StartPayload(False, "demo"),
        [],
    )
    assert payload_of(Command.ESTOP, None) == (StopPayload(None), [])
    # A command that takes no body gets none, whatever was sent (HTTP does not read it).
    assert payload_of(Command.PAUSE, {"anything": 1}) == (None, [])


def test_an_unknown_field_is_refused_as_over_http() -> None:
    _, problems = payload_of(Command.START, {"contourMatching": False})
    assert [(p["field"], p["type"]) for p in problems] == [("contourMatching", "extra_forbidden")]


@pytest.mark.parametrize(
    ("args", "body"),
    [
        ((), {}),
        ((ua.Variant("", ua.VariantType.String),), {}),
        ((ua.Variant(None, ua.VariantType.Null),), {}),
        (
            (ua.Variant("demo", ua.VariantType.String),),
            {"contour_matching": False, "workpiece_id": "demo"},
        ),
    ],
)
def test_starts_workpiece_id_is_the_routes_body(args: tuple[object, ...], body: object) -> None:
    assert body_of(START, args) == (body, [])


def test_a_number_in_workpiece_id_reaches_the_model_as_a_number() -> None:
    body, problems = body_of(START, (ua.Variant(math.nan, ua.VariantType.Double),))
    assert problems == []
    _, problems = payload_of(Command.START, body)
    assert [p["field"] for p in problems] == ["workpiece_id"]


def test_more_arguments_than_declared_are_refused_and_none_read_elsewhere() -> None:
    two = (ua.Variant("demo", ua.VariantType.String), ua.Variant("x", ua.VariantType.String))
    _, problems = body_of(START, two)
    assert [p["field"] for p in problems] == ["arguments"]
    assert body_of(PAUSE, two) == (None, [])
