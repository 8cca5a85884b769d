"""Framing and JSON-RPC helper edge cases, with plain byte strings (no sockets)."""

from __future__ import annotations

import json
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from server.drivers.jsonlines import (
    INVALID_REQUEST,
    PARSE_ERROR,
    JsonRpcError,
    LineDecoder,
    LineTooLong,
    MalformedLine,
    encode_message,
    make_error,
    make_request,
    make_result,
    parse_request,
)


def test_one_complete_message() -> None:
    assert LineDecoder().feed(b'{"a": 1}\n') == [{"a": 1}]


def test_message_split_in_the_middle_is_reassembled() -> None:
    decoder = LineDecoder()
    assert decoder.feed(b'{"jsonrpc": "2.0", "me') == []
    assert decoder.buffered > 0
    assert decoder.feed(b'thod": "stop", "id": 7}\n') == [
        {"jsonrpc": "2.0", "method": "stop", "id": 7}
    ]
    assert decoder.buffered == 0


def test_split_inside_a_multibyte_utf8_character() -> None:
    raw = encode_message({"label": "bead 90° côté"})
    cut = raw.index("°".encode()) + 1  # between the two bytes of "°"
    decoder = LineDecoder()
    assert decoder.feed(raw[:cut]) == []
    assert decoder.feed(raw[cut:]) == [{"label": "bead 90° côté"}]


def test_byte_by_byte_feeding() -> None:
    raw = encode_message({"pose": [400.0, 0.0, 200.0, 180.0, 0.0, 0.0], "µ": "✓"})
    decoder = LineDecoder()
    out: list[Any] = []
    for i in range(len(raw)):
        out += decoder.feed(raw[i : i + 1])
    assert out == [json.loads(raw)]


def test_several_messages_in_one_chunk_come_out_in_order() -> None:
    chunk = b'{"id": 1}\n{"id": 2}\n{"id": 3}\n{"id": 4'
    decoder = LineDecoder()
    assert decoder.feed(chunk) == [{"id": 1}, {"id": 2}, {"id": 3}]
    assert decoder.feed(b"}\n") == [{"id": 4}]


def test_empty_and_blank_lines_are_skipped_and_crlf_tolerated() -> None:
    decoder = LineDecoder()
    assert decoder.feed(b'\n\n  \n\r\n{"id": 1}\r\n\n{"id": 2}\n') == [{"id": 1}, {"id": 2}]


def test_malformed_json_is_a_value_and_decoding_continues() -> None:
    decoder = LineDecoder()
    out = decoder.feed(b'{"id": 1}\n{not json\n{"id": 2}\n')
    assert out[0] == {"id": 1}
    assert isinstance(out[1], MalformedLine)
    assert out[1].raw == b"{not json"
    assert "not valid JSON" in out[1].reason
    assert out[2] == {"id": 2}


def test_invalid_utf8_is_malformed() -> None:
    (bad,) = LineDecoder().feed(b'{"a": "\xff\xfe"}\n')
    assert isinstance(bad, MalformedLine)
    assert "UTF-8" in bad.reason


def test_nan_and_infinity_are_not_json() -> None:
    out = LineDecoder().feed(b"[NaN]\n[Infinity]\n")
    assert all(isinstance(m, MalformedLine) for m in out)


def test_line_at_the_limit_is_accepted() -> None:
    decoder = LineDecoder(max_line_bytes=16)
    line = b'"' + b"x" * 14 + b'"'
    assert len(line) == 16
    assert decoder.feed(line + b"\n") == ["x" * 14]


def test_overlong_complete_line_raises_and_keeps_the_good_ones() -> None:
    decoder = LineDecoder(max_line_bytes=32)
    chunk = b'{"id": 1}\n"' + b"x" * 64 + b'"\n{"id": 2}\n{"id":'
    with pytest.raises(LineTooLong) as caught:
        decoder.feed(chunk)
    assert caught.value.limit == 32
    assert caught.value.messages == [{"id": 1}, {"id": 2}]
    assert decoder.feed(b" 3}\n") == [{"id": 3}]


def test_overlong_partial_line_raises_once_then_resynchronises() -> None:
    decoder = LineDecoder(max_line_bytes=32)
    assert decoder.feed(b"y" * 20) == []
    with pytest.raises(LineTooLong):
        decoder.feed(b"y" * 20)
    assert decoder.buffered == 0  # memory is released at once
    assert decoder.feed(b"y" * 100) == []  # still inside the same line: no second error
    assert decoder.feed(b'yyy\n{"id": 9}\n') == [{"id": 9}]


def test_reset_forgets_a_partial_line() -> None:
    decoder = LineDecoder()
    decoder.feed(b'{"id": ')
    decoder.reset()
    assert decoder.feed(b'{"id": 1}\n') == [{"id": 1}]


def test_encode_message_is_one_utf8_line() -> None:
    raw = encode_message({"text": "line1\nline2 °", "n": 1.5})
    assert raw.endswith(b"\n")
    assert raw.count(b"\n") == 1  # the inner newline is escaped
    assert "°".encode() in raw
    assert json.loads(raw) == {"text": "line1\nline2 °", "n": 1.5}


def test_encode_message_refuses_nan() -> None:
    with pytest.raises(ValueError):
        encode_message({"x": float("nan")})


json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**53), 2**53)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(), inner, max_size=4),
    max_leaves=12,
)


@given(st.lists(json_values, min_size=1, max_size=6), st.data())
def test_any_split_of_a_stream_decodes_to_the_same_messages(
    messages: list[Any], data: st.DataObject
) -> None:
    stream = b"".join(encode_message(m) for m in messages)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=8)))
    decoder = LineDecoder()
    out: list[Any] = []
    previous = 0
    for cut in [*cuts, len(stream)]:
        out += decoder.feed(stream[previous:cut])
        previous = cut
    assert out == messages
    assert decoder.buffered == 0


# --- JSON-RPC helpers ----------------------------------------------------------


def test_request_result_and_error_shapes() -> None:
    assert make_request("moveL", [[1, 2, 3, 4, 5, 6], 10, 100], 3) == {
        "jsonrpc": "2.0",
        "method": "moveL",
        "params": [[1, 2, 3, 4, 5, 6], 10, 100],
        "id": 3,
    }
    assert make_request("stop") == {"jsonrpc": "2.0", "method": "stop"}  # a notification
    assert make_result(3, True) == {"jsonrpc": "2.0", "id": 3, "result": True}
    assert make_error(None, PARSE_ERROR, "parse error") == {
        "jsonrpc": "2.0",
        "id": None,
        "error": {"code": -32700, "message": "parse error"},
    }
    assert make_error(4, 1001, "x", {"axis": "x"})["error"]["data"] == {"axis": "x"}


def test_parse_request_accepts_positional_named_and_notifications() -> None:
    request = parse_request({"jsonrpc": "2.0", "method": "getPosition", "id": 1})
    assert (request.method, request.params, request.id) == ("getPosition", [], 1)
    assert not request.is_notification
    named = parse_request({"jsonrpc": "2.0", "method": "moveJ", "params": {"speed": 5}, "id": "a"})
    assert named.params == {"speed": 5}
    assert parse_request({"jsonrpc": "2.0", "method": "stop"}).is_notification


@pytest.mark.parametrize(
    "message",
    [
        [{"jsonrpc": "2.0", "method": "stop", "id": 1}],  # batch
        "stop",
        {"method": "stop", "id": 1},
        {"jsonrpc": "1.0", "method": "stop", "id": 1},
        {"jsonrpc": "2.0", "method": 5, "id": 1},
        {"jsonrpc": "2.0", "method": "stop", "params": 5, "id": 1},
        {"jsonrpc": "2.0", "method": "stop", "id": [1]},
        {"jsonrpc": "2.0", "method": "stop", "id": True},
    ],
)
def test_parse_request_refuses_invalid_requests(message: Any) -> None:
    with pytest.raises(JsonRpcError) as caught:
        parse_request(message)
    assert caught.value.code == INVALID_REQUEST
