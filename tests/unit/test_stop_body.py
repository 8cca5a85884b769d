"""How the stop lane takes a stop's body: as the route would, or not at all.

The lane finishes a stop itself only with a body the route's request model accepts
(server/api/stop_lane.py); any other body goes on to the route, whose 422 words it
as for every command. So the lane must never take a body FastAPI would refuse.
"""

from __future__ import annotations

import json

import pytest

from server.api.stop_lane import _payload_of, made_without_reason
from server.commands.catalogue import CATALOGUE
from server.core.machine.events import StopPayload

ESTOP = next(spec for spec in CATALOGUE if spec.stop and spec.path == "/estop")


def scope(content_type: str | None) -> dict[str, object]:
    headers = [] if content_type is None else [(b"content-type", content_type.encode())]
    return {"type": "http", "method": "POST", "path": "/estop", "headers": headers}


@pytest.mark.parametrize(
    ("content_type", "body", "reason"),
    [
        (None, b"", None),
        ("application/json", b"", None),
        ("text/plain", b"", None),  # no body: no model, whatever the type says
        ("application/json", b"null", None),
        ("application/json", b"{}", None),
        ("application/json", b'{"reason": "hand in the cell"}', "hand in the cell"),
        ("application/json; charset=utf-8", b'{"reason": "r"}', "r"),
        ("application/problem+json", b'{"reason": "r"}', "r"),
    ],
)
def test_a_body_the_route_would_take_gives_its_reason(
    content_type: str | None, body: bytes, reason: str | None
) -> None:
    assert _payload_of(ESTOP, scope(content_type), body) == StopPayload(reason)


@pytest.mark.parametrize(
    ("content_type", "body"),
    [
        ("application/json", b"{not json"),
        ("application/json", b'{"reason": 5}'),  # a strict str
        ("application/json", b'{"reason": "r", "extra": 1}'),  # an unknown key
        ("application/json", json.dumps({"reason": "x" * 201}).encode()),  # over 200
        ("application/json", b"[1]"),
        ("application/json", b'"a reason"'),
        ("application/json", b"\xff\xfe\xfa"),  # not text
        ("text/plain", b'{"reason": "r"}'),  # bytes, which no model accepts
        (None, b'{"reason": "r"}'),  # the same: FastAPI's strict content type
        ("multipart/form-data; boundary=x", b"--x--"),
    ],
)
def test_a_body_the_route_would_refuse_goes_on_to_the_route(content_type: str, body: bytes) -> None:
    assert _payload_of(ESTOP, scope(content_type), body) is None


def test_a_stop_made_without_its_reason_says_so_in_the_cells_answer() -> None:
    answer = {"accepted": True, "event_id": "e1", "state": "ERROR", "message": "m", "run_id": None}
    assert made_without_reason(answer) == {
        "accepted": True,
        "event_id": "e1",
        "state": "ERROR",
        "message": "the stop was made without its reason: m",
    }
