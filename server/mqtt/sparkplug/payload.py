"""Sparkplug B payloads on the wire: the protobuf `Payload` and `Metric` messages, by hand.

Why by hand and not generated code: the cell sends and reads only scalar metrics
(integers, doubles, booleans, strings), which are a few protobuf fields; the wire
format of those is small and fixed (varints, 64-bit doubles, length-delimited
strings), and writing it here keeps the server free of a protobuf runtime and
of generated code. The field numbers and the data type numbers are those of the
Eclipse Tahu schema (`sparkplug_b.proto`, package org.eclipse.tahu.protobuf); the
tests decode what this writes with a Sparkplug decoder from PyPI built from
that schema, and this reads what that encoder writes.

Sparkplug's own rules kept here: a signed integer travels as its two's
complement in the unsigned field (Int8 to Int32 in `int_value`, Int64 in
`long_value`); a DateTime is milliseconds since the epoch in `long_value`; a
null value is `is_null` with no value. Pure: no I/O, no clock.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Final


class DataType(IntEnum):
    """Sparkplug B's metric data types (the scalar ones the cell uses)."""

    INT8 = 1
    INT16 = 2
    INT32 = 3
    INT64 = 4
    UINT8 = 5
    UINT16 = 6
    UINT32 = 7
    UINT64 = 8
    FLOAT = 9
    DOUBLE = 10
    BOOLEAN = 11
    STRING = 12
    DATETIME = 13
    TEXT = 14


Value = int | float | bool | str | None

# Metric fields (sparkplug_b.proto, Payload.Metric).
_NAME, _ALIAS, _TIMESTAMP, _DATATYPE, _IS_NULL = 1, 2, 3, 4, 7
_INT, _LONG, _FLOAT, _DOUBLE, _BOOLEAN, _STRING = 10, 11, 12, 13, 14, 15
# Payload fields.
_P_TIMESTAMP, _P_METRICS, _P_SEQ, _P_UUID = 1, 2, 3, 4

_VARINT, _FIXED64, _LENGTH, _FIXED32 = 0, 1, 2, 5
_INT_TYPES: Final = {DataType.INT8, DataType.INT16, DataType.INT32}
_UINT_TYPES: Final = {DataType.UINT8, DataType.UINT16, DataType.UINT32}
_LONG_TYPES: Final = {DataType.INT64, DataType.UINT64, DataType.DATETIME}
_TEXT_TYPES: Final = {DataType.STRING, DataType.TEXT}
_BITS: Final = {DataType.INT8: 8, DataType.INT16: 16, DataType.INT32: 32, DataType.INT64: 64}


class PayloadError(ValueError):
    """Bytes that are not a Sparkplug B payload this codec reads."""


@dataclass(frozen=True, slots=True)
class Metric:
    """One metric: its name, data type and value (None: null), and when it was taken (ms)."""

    name: str
    datatype: DataType
    value: Value
    timestamp: int | None = None
    alias: int | None = None


@dataclass(frozen=True, slots=True)
class Payload:
    """A Sparkplug B payload: when (ms), its sequence number (None for NDEATH), the metrics."""

    timestamp: int
    metrics: tuple[Metric, ...] = field(default_factory=tuple)
    seq: int | None = None
    uuid: str | None = None


# --- writing ---------------------------------------------------------------------------


def _varint(value: int) -> bytes:
    out = bytearray()
    value &= (1 << 64) - 1
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def _key(number: int, wire: int) -> bytes:
    return _varint((number << 3) | wire)


def _length(number: int, data: bytes) -> bytes:
    return _key(number, _LENGTH) + _varint(len(data)) + data


def _value_field(datatype: DataType, value: int | float | bool | str) -> bytes:
    if datatype is DataType.BOOLEAN:
        return _key(_BOOLEAN, _VARINT) + _varint(1 if value else 0)
    if datatype in _TEXT_TYPES:
        return _length(_STRING, str(value).encode())
    if datatype is DataType.DOUBLE:
        return _key(_DOUBLE, _FIXED64) + struct.pack("<d", float(value))
    if datatype is DataType.FLOAT:
        return _key(_FLOAT, _FIXED32) + struct.pack("<f", float(value))
    number = int(value)
    if datatype in _INT_TYPES or datatype in _UINT_TYPES:
        return _key(_INT, _VARINT) + _varint(number & 0xFFFFFFFF)
    if datatype in _LONG_TYPES:
        return _key(_LONG, _VARINT) + _varint(number & 0xFFFFFFFFFFFFFFFF)
    raise PayloadError(f"data type {datatype.name} is not one this codec writes")


def encode_metric(metric: Metric) -> bytes:
    """One `Payload.Metric` message."""
    out = _length(_NAME, metric.name.encode())
    if metric.alias is not None:
        out += _key(_ALIAS, _VARINT) + _varint(metric.alias)
    if metric.timestamp is not None:
        out += _key(_TIMESTAMP, _VARINT) + _varint(metric.timestamp)
    out += _key(_DATATYPE, _VARINT) + _varint(int(metric.datatype))
    if metric.value is None:
        return out + _key(_IS_NULL, _VARINT) + _varint(1)
    return out + _value_field(metric.datatype, metric.value)


def encode(payload: Payload) -> bytes:
    """A `Payload` message: timestamp, metrics, seq (when it has one), uuid."""
    out = _key(_P_TIMESTAMP, _VARINT) + _varint(payload.timestamp)
    for metric in payload.metrics:
        out += _length(_P_METRICS, encode_metric(metric))
    if payload.seq is not None:
        out += _key(_P_SEQ, _VARINT) + _varint(payload.seq)
    if payload.uuid is not None:
        out += _length(_P_UUID, payload.uuid.encode())
    return out


# --- reading ---------------------------------------------------------------------------


def _read_varint(data: bytes, at: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        if at >= len(data) or shift > 63:
            raise PayloadError("a varint runs past the end")
        byte = data[at]
        at += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, at
        shift += 7


def _fields(data: bytes) -> list[tuple[int, int, int | bytes]]:
    """Each field of a message: its number, wire type and raw value (int or bytes)."""
    found: list[tuple[int, int, int | bytes]] = []
    at = 0
    while at < len(data):
        key, at = _read_varint(data, at)
        number, wire = key >> 3, key & 7
        raw: int | bytes
        if wire == _VARINT:
            raw, at = _read_varint(data, at)
        elif wire == _FIXED64:
            raw, at = data[at : at + 8], at + 8
        elif wire == _FIXED32:
            raw, at = data[at : at + 4], at + 4
        elif wire == _LENGTH:
            size, at = _read_varint(data, at)
            raw, at = data[at : at + size], at + size
        else:
            raise PayloadError(f"wire type {wire} is not one Sparkplug B uses")
        if at > len(data):
            raise PayloadError("a field runs past the end")
        found.append((number, wire, raw))
    return found


def _signed(value: int, bits: int) -> int:
    value &= (1 << bits) - 1
    return value - (1 << bits) if value >> (bits - 1) else value


def decode_metric(data: bytes) -> Metric:
    """One `Payload.Metric` message; the value as its data type says."""
    name, alias, timestamp, datatype, is_null = "", None, None, 0, False
    raw: dict[int, int | bytes] = {}
    for number, _, value in _fields(data):
        if number == _NAME and isinstance(value, bytes):
            name = value.decode()
        elif number == _ALIAS and isinstance(value, int):
            alias = value
        elif number == _TIMESTAMP and isinstance(value, int):
            timestamp = value
        elif number == _DATATYPE and isinstance(value, int):
            datatype = value
        elif number == _IS_NULL and isinstance(value, int):
            is_null = bool(value)
        else:
            raw[number] = value
    try:
        kind = DataType(datatype)
    except ValueError:
        raise PayloadError(f"metric {name!r}: data type {datatype} is not one this reads") from None
    return Metric(name, kind, None if is_null else _value_of(kind, raw), timestamp, alias)


def _value_of(kind: DataType, raw: dict[int, int | bytes]) -> Value:
    if kind is DataType.BOOLEAN:
        return bool(raw.get(_BOOLEAN, 0))
    if kind in _TEXT_TYPES:
        text = raw.get(_STRING, b"")
        return text.decode() if isinstance(text, bytes) else None
    if kind is DataType.DOUBLE:
        packed = raw.get(_DOUBLE)
        return struct.unpack("<d", packed)[0] if isinstance(packed, bytes) else 0.0
    if kind is DataType.FLOAT:
        packed = raw.get(_FLOAT)
        return struct.unpack("<f", packed)[0] if isinstance(packed, bytes) else 0.0
    number = raw.get(_LONG if kind in _LONG_TYPES else _INT, 0)
    if not isinstance(number, int):
        return None
    return _signed(number, _BITS[kind]) if kind in _BITS else number


def decode(data: bytes) -> Payload:
    """A `Payload` message; metrics of types this codec does not read raise PayloadError."""
    timestamp, seq, uuid = 0, None, None
    metrics: list[Metric] = []
    for number, _, value in _fields(bytes(data)):
        if number == _P_TIMESTAMP and isinstance(value, int):
            timestamp = value
        elif number == _P_METRICS and isinstance(value, bytes):
            metrics.append(decode_metric(value))
        elif number == _P_SEQ and isinstance(value, int):
            seq = value
        elif number == _P_UUID and isinstance(value, bytes):
            uuid = value.decode()
    return Payload(timestamp, tuple(metrics), seq, uuid)
