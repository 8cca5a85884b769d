"""The frame the hub writes to every client is the frame the websockets protocol would send."""

from __future__ import annotations

import pytest
from fastapi import APIRouter, Request
from websockets.frames import Frame, Opcode
from websockets.streams import StreamReader

from server.api.direct_json import DirectJsonRoute
from server.api.schemas import AllowedView
from server.api.ws import WebSocketHub
from server.core.infra.bus import BusMessage


def _parsed(frame: bytes) -> Frame:
    reader = StreamReader()
    reader.feed_data(frame)
    parser = Frame.parse(reader.read_exact, mask=False)
    try:
        next(parser)
    except StopIteration as done:
        return done.value
    raise AssertionError("incomplete frame")


@pytest.mark.parametrize("size", [10, 200, 70_000])  # each of the three length encodings
def test_the_shared_frame_is_a_text_frame_of_the_encoded_message(size: int) -> None:
    hub = WebSocketHub(max_clients=10, buffer=8)
    message = BusMessage(1, "state_changed", 1.5, {"note": "é" * size})
    frame = _parsed(hub.frame(message))
    assert frame.opcode is Opcode.TEXT and frame.fin
    assert frame.data.decode() == hub.encode(message)
    assert hub.frame(message) is hub.frame(message)  # built once


def test_a_direct_route_refuses_an_endpoint_that_reads_more_than_the_request() -> None:
    router = APIRouter()

    async def reads_a_query(request: Request, name: str) -> dict:
        return {}

    with pytest.raises(TypeError, match="request alone"):
        router.add_api_route(
            "/x", reads_a_query, response_model=AllowedView, route_class_override=DirectJsonRoute
        )
