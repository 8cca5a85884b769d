"""The cell's Sparkplug B codec against Eclipse Tahu's schema, read by another implementation.

What the cell writes (server/mqtt/sparkplug/payload.py, by hand) is parsed by the
protobuf runtime with the code generated from `sparkplug_b.proto` that
esio-spb-builder ships, and what that writes the cell reads: names, types, values
(signed integers as Sparkplug's two's complement, nulls, doubles), seq and
timestamps survive both ways.
"""

from __future__ import annotations

import pytest
from esio_spb_builder.core import sparkplug_b_pb2 as tahu
from hypothesis import given
from hypothesis import strategies as st

from server.core.machine.transitions import Command
from server.mqtt.sparkplug import metrics as sp
from server.mqtt.sparkplug.payload import (
    DataType,
    Metric,
    Payload,
    PayloadError,
    decode,
    encode,
)

VALUE_FIELD = {
    DataType.INT32: "int_value",
    DataType.INT64: "long_value",
    DataType.UINT64: "long_value",
    DataType.DATETIME: "long_value",
    DataType.DOUBLE: "double_value",
    DataType.BOOLEAN: "boolean_value",
    DataType.STRING: "string_value",
}


def _tahu_value(metric: tahu.Payload.Metric) -> object:
    if metric.is_null:
        return None
    raw = getattr(metric, VALUE_FIELD[DataType(metric.datatype)])
    if metric.datatype == DataType.INT32:
        return raw - (1 << 32) if raw >= 1 << 31 else raw
    if metric.datatype == DataType.INT64:
        return raw - (1 << 64) if raw >= 1 << 63 else raw
    return raw


values = st.one_of(
    st.tuples(st.just(DataType.INT32), st.integers(-(2**31), 2**31 - 1)),
    st.tuples(st.just(DataType.INT64), st.integers(-(2**63), 2**63 - 1)),
    st.tuples(st.just(DataType.UINT64), st.integers(0, 2**64 - 1)),
    st.tuples(st.just(DataType.DATETIME), st.integers(0, 2**53)),
    st.tuples(st.just(DataType.DOUBLE), st.floats(allow_nan=False)),
    st.tuples(st.just(DataType.BOOLEAN), st.booleans()),
    st.tuples(st.just(DataType.STRING), st.text()),
    st.tuples(st.sampled_from(list(VALUE_FIELD)), st.none()),
)
metrics = st.lists(
    st.tuples(st.text(min_size=1, max_size=40), values, st.integers(0, 2**48)), max_size=8
)


@given(metrics, st.integers(0, 255), st.integers(0, 2**48))
def test_tahu_reads_what_the_cell_writes(items, seq: int, timestamp: int) -> None:
    sent = Payload(timestamp, tuple(Metric(n, kind, v, at) for n, (kind, v), at in items), seq=seq)
    read = tahu.Payload.FromString(encode(sent))
    assert read.timestamp == timestamp and read.seq == seq
    assert [(m.name, m.datatype, _tahu_value(m), m.timestamp) for m in read.metrics] == [
        (n, int(kind), v, at) for n, (kind, v), at in items
    ]


@given(metrics, st.integers(0, 255), st.integers(0, 2**48))
def test_the_cell_reads_what_tahu_writes(items, seq: int, timestamp: int) -> None:
    written = tahu.Payload(timestamp=timestamp, seq=seq)
    for name, (kind, value), at in items:
        metric = written.metrics.add(name=name, datatype=int(kind), timestamp=at)
        if value is None:
            metric.is_null = True
        elif isinstance(value, int) and not isinstance(value, bool) and value < 0:
            bits = 32 if kind is DataType.INT32 else 64
            setattr(metric, VALUE_FIELD[kind], value + (1 << bits))
        else:
            setattr(metric, VALUE_FIELD[kind], value)
    read = decode(written.SerializeToString())
    assert (read.timestamp, read.seq) == (timestamp, seq)
    assert [(m.name, m.datatype, m.value, m.timestamp) for m in read.metrics] == [
        (n, kind, v, at) for n, (kind, v), at in items
    ]


def test_a_death_certificate_has_no_seq() -> None:
    death = tahu.Payload.FromString(encode(Payload(5, (sp.bd_seq_metric(7, 5),))))
    assert not death.HasField("seq")
    assert [(m.name, m.datatype, m.long_value) for m in death.metrics] == [("bdSeq", 4, 7)]


@pytest.mark.parametrize("garbage", [b"\x0a\xff", b"\x12\x05\x0a", b"\x0f"])
def test_bytes_that_are_no_payload_are_refused(garbage: bytes) -> None:
    with pytest.raises(PayloadError):
        decode(garbage)


def test_a_dcmd_asks_only_for_known_commands_written_true() -> None:
    asked = [
        Metric("Command/Start", DataType.BOOLEAN, True),
        Metric("Command/Pause", DataType.BOOLEAN, False),
        Metric("Command/Estop", DataType.STRING, "true"),
        Metric("Command/Nonsense", DataType.BOOLEAN, True),
        Metric("Command/Estop", DataType.BOOLEAN, True),
    ]
    assert sp.commands_in(asked) == [
        ("Command/Start", Command.START),
        ("Command/Estop", Command.ESTOP),
    ]
    # Every command a body is not required for, and none that needs one.
    assert "Command/Jog" not in sp.COMMAND_METRICS
    assert sp.COMMAND_METRICS["Command/CalibrateRobot"] is Command.CALIBRATE_ROBOT


def test_ddata_holds_only_what_changed() -> None:
    before = {"State": "IDLE", "PackML/State": 4, "OEE/OEE": None, "Counts/Good": 1}
    after = {"State": "EXECUTING_TRAJECTORY", "PackML/State": 6, "OEE/OEE": None, "Counts/Good": 1}
    changed = sp.changed_metrics(before, after, 9)
    assert [(m.name, m.value, m.datatype) for m in changed] == [
        ("State", "EXECUTING_TRAJECTORY", DataType.STRING),
        ("PackML/State", 6, DataType.INT32),
    ]
