"""The glue register map: scaling, range checks, alarm bits, and the document staying in step."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from server.drivers import glue_registers as regs
from server.drivers.base import GlueStatus

DOC = Path(__file__).resolve().parents[2] / "docs" / "glue-register-map.md"


def _status_block(**values: int) -> list[int]:
    block = [0] * regs.STATUS_COUNT
    for name, raw in values.items():
        block[regs.register_by_name(name).address - regs.STATUS_ADDRESS] = raw
    return block


# --- scaling -----------------------------------------------------------------------


@given(st.floats(min_value=0.0, max_value=1000.0))
def test_flow_round_trips_within_half_a_count(ml_min: float) -> None:
    raw = regs.encode_flow(ml_min)
    assert 0 <= raw <= 10000
    assert abs(regs.FLOW_SETPOINT.decode(raw) - ml_min) <= 0.05 + 1e-9


@given(st.floats(min_value=0.0, max_value=150.0))
def test_pressure_round_trips_within_half_a_count(psi: float) -> None:
    raw = regs.encode_pressure(psi)
    assert abs(regs.PRESSURE_SETPOINT.decode(raw) - psi) <= 0.05 + 1e-9


@given(st.integers(min_value=-400, max_value=1500))
def test_temperature_is_signed_and_round_trips(tenths: int) -> None:
    celsius = tenths / 10
    raw = regs.TEMPERATURE.encode(celsius)
    assert 0 <= raw <= 0xFFFF
    assert regs.TEMPERATURE.decode(raw) == pytest.approx(celsius)


def test_negative_temperature_is_twos_complement() -> None:
    assert regs.TEMPERATURE.encode(-0.1) == 0xFFFF
    assert regs.TEMPERATURE.decode(0xFF85) == pytest.approx(-12.3)


def test_exact_setpoints_encode_to_whole_counts() -> None:
    assert regs.encode_flow(30.0) == 300
    assert regs.encode_flow(1000.0) == 10000
    assert regs.encode_pressure(40.0) == 400
    assert regs.encode_valve(True) == 1
    assert regs.encode_valve(False) == 0


def test_measurements_saturate_only_when_asked() -> None:
    assert regs.PRESSURE_MEASURED.encode(999.0, clamp=True) == 3000
    with pytest.raises(ValueError, match="PRESSURE_MEASURED"):
        regs.PRESSURE_MEASURED.encode(999.0)


def test_decode_refuses_values_a_register_cannot_hold() -> None:
    with pytest.raises(ValueError, match="FLOW_MEASURED"):
        regs.FLOW_MEASURED.decode(70000)


# --- range errors name the field and its limits ---------------------------------


@pytest.mark.parametrize("value", [-0.1, 1000.1, 5000.0])
def test_flow_out_of_range_names_field_and_limits(value: float) -> None:
    with pytest.raises(ValueError, match=r"FLOW_SETPOINT must be between 0 and 1000 ml/min"):
        regs.encode_flow(value)


@pytest.mark.parametrize("value", [-1.0, 150.5])
def test_pressure_out_of_range_names_field_and_limits(value: float) -> None:
    with pytest.raises(ValueError, match=r"PRESSURE_SETPOINT must be between 0 and 150 PSI"):
        regs.encode_pressure(value)


@pytest.mark.parametrize("value", [float("nan"), float("inf"), "12"])
def test_non_numbers_are_refused(value: object) -> None:
    with pytest.raises(ValueError, match="FLOW_SETPOINT needs a finite number"):
        regs.encode_flow(value)  # type: ignore[arg-type]


# --- alarms and the status block ----------------------------------------------------


def test_alarm_names_from_bits() -> None:
    assert regs.alarm_names(0) == ()
    assert regs.alarm_names(0b10) == ("HIGH_PRESSURE",)
    assert regs.alarm_names(0b101001) == ("LOW_PRESSURE", "NOZZLE_BLOCKED", "VALVE_FAULT")


def test_undefined_alarm_bits_are_kept_not_dropped() -> None:
    assert regs.alarm_names(1 << 6 | 1 << 15) == ("BIT6", "BIT15")


@given(st.integers(min_value=0, max_value=0b111111))
def test_alarm_bits_and_names_are_inverse(bits: int) -> None:
    assert regs.alarm_bits(regs.alarm_names(bits)) == bits


def test_unknown_alarm_name_is_refused_with_the_known_ones() -> None:
    with pytest.raises(ValueError, match=r"unknown glue alarm 'FIRE'.*NOZZLE_BLOCKED"):
        regs.alarm_bits(["FIRE"])


def test_decode_status() -> None:
    block = _status_block(
        VALVE_STATE=1,
        FLOW_SETPOINT_ACTIVE=300,
        PRESSURE_SETPOINT_ACTIVE=400,
        FLOW_MEASURED=297,
        PRESSURE_MEASURED=401,
        TEMPERATURE=0xFFFF,
        ALARM_BITS=int(regs.Alarm.RESERVOIR_LOW),
        UPTIME=42,
        DISPENSED_HIGH=2,
        DISPENSED_LOW=1500,
    )
    assert regs.decode_status(block) == GlueStatus(
        valve_open=True,
        flow_setpoint_ml_min=30.0,
        pressure_setpoint_psi=40.0,
        flow_ml_min=29.7,
        pressure_psi=40.1,
        temperature_c=-0.1,
        alarms=("RESERVOIR_LOW",),
        dispensed_ml=132.572,  # 2 × 65.536 + 1.5 ml
    )
    assert regs.decode_uptime(block) == 42


def test_decode_status_needs_the_whole_block() -> None:
    with pytest.raises(ValueError, match="10 registers from 100, got 3"):
        regs.decode_status([0, 0, 0])


@given(st.floats(min_value=0.0, max_value=regs.TOTAL_WRAP_ML - 1.0))
def test_the_totaliser_round_trips_to_the_microlitre(ml: float) -> None:
    high, low = regs.encode_dispensed(ml)
    decoded = regs.decode_status(_status_block(DISPENSED_HIGH=high, DISPENSED_LOW=low))
    assert decoded.dispensed_ml == pytest.approx(ml, abs=0.0005)


def test_the_totaliser_wraps_at_two_to_the_32_microlitres() -> None:
    assert regs.encode_dispensed(regs.TOTAL_WRAP_ML + 0.002) == (0, 2)
    assert regs.dispensed_since(regs.TOTAL_WRAP_ML - 0.001, 0.002) == pytest.approx(0.003)
    assert regs.dispensed_since(1.0, 3.5) == 2.5
    assert regs.dispensed_since(2000.0, 1.0) == 1.0  # not near its top: powered up again


def test_map_is_consistent() -> None:
    names = [r.name for r in regs.REGISTERS]
    assert len(set(names)) == len(names)
    addresses = [r.address for r in regs.REGISTERS]
    assert len(set(addresses)) == len(addresses), "addresses are unique across tables"
    status_addresses = [r.address for r in regs.INPUT_REGISTERS]
    assert status_addresses == list(
        range(regs.STATUS_ADDRESS, regs.STATUS_ADDRESS + regs.STATUS_COUNT)
    )
    assert all(r.writable for r in regs.HOLDING_REGISTERS)
    assert not any(r.writable for r in regs.INPUT_REGISTERS)
    for r in regs.REGISTERS:
        assert r.encode(r.maximum) <= 0xFFFF, r.name


def test_exception_text() -> None:
    assert regs.exception_text(2) == "Modbus exception 2 (illegal data address)"
    assert regs.exception_text(99) == "Modbus exception 99 (unknown)"


# --- the document cannot drift ---------------------------------------------------------


def _table_rows(text: str, header_start: str) -> list[list[str]]:
    """Cells of the markdown table whose header row starts with `header_start`."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(header_start))
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        rows.append([cell.strip() for cell in line.strip().strip("|").split("|")])
    return rows


def test_every_register_appears_in_the_doc_table() -> None:
    rows = _table_rows(DOC.read_text(encoding="utf-8"), "| Address | Function codes | Name")
    by_name = {re.sub(r"`", "", row[2]): row for row in rows}
    assert set(by_name) == {r.name for r in regs.REGISTERS}, (
        "doc table and map name different registers"
    )
    for r in regs.REGISTERS:
        address, codes, _name, unit, scale, value_range, access = by_name[r.name]
        assert address == str(r.address), r.name
        expected_codes = "FC3 read, FC6/FC16 write" if r.writable else "FC4"
        assert codes == expected_codes, r.name
        assert unit == (r.unit or "-"), r.name
        assert scale == f"{r.scale:g}", r.name
        assert value_range.startswith(f"{r.minimum:g} "), r.name
        assert f"- {r.maximum:g}" in value_range, r.name
        assert access == ("read/write" if r.writable else "read-only"), r.name


def test_every_alarm_bit_appears_in_the_doc() -> None:
    rows = _table_rows(DOC.read_text(encoding="utf-8"), "| Bit | Value | Name")
    documented = {row[2].strip("`"): (int(row[0]), int(row[1], 16)) for row in rows}
    expected = {a.name: (int(a).bit_length() - 1, int(a)) for a in regs.Alarm}
    assert documented == expected


def test_doc_states_the_serial_settings() -> None:
    text = DOC.read_text(encoding="utf-8")
    assert str(regs.BAUDRATE) in text
    assert "8N1" in text and regs.PARITY == "N" and regs.BYTESIZE == 8 and regs.STOPBITS == 1
    assert f"| Device id      | {regs.DEFAULT_DEVICE_ID} " in text
