"""The Modbus glue driver against the simulator over real 127.0.0.1 sockets (no Modbus mocks)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import signal
import socket
import sys
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import pytest

from server.common.errors import DeviceDisconnected, DeviceError, DeviceTimeout
from server.drivers import glue_registers as regs
from server.drivers.base import DeviceFault, GlueDispenser
from server.drivers.glue_line import COMMAND, POLL, URGENT, LineArbiter
from server.drivers.glue_modbus import ModbusGlueDispenser
from server.drivers.sim.glue_sim import GlueSimulator

TIMEOUT = 0.5  # the driver's glue_system_timeout in these tests
POLL_S = 0.05
ROOT = Path(__file__).resolve().parents[2]


async def wait_until(predicate: Callable[[], bool], within: float = 5.0) -> None:
    """Poll `predicate` until true; fail the test (not hang) after `within` s."""
    deadline = time.monotonic() + within
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"condition not met within {within} s")
        await asyncio.sleep(0.01)


def codes(faults: list[DeviceFault], code: str) -> list[DeviceFault]:
    return [f for f in faults if f.code == code]


@pytest.fixture
async def sim() -> AsyncIterator[GlueSimulator]:
    simulator = GlueSimulator(seed=7)
    await simulator.start()
    yield simulator
    await simulator.stop()


@pytest.fixture
def faults() -> list[DeviceFault]:
    return []


@pytest.fixture
async def glue(sim: GlueSimulator, faults: list[DeviceFault]) -> AsyncIterator[ModbusGlueDispenser]:
    dispenser = ModbusGlueDispenser.tcp(
        "127.0.0.1", sim.port, timeout=TIMEOUT, poll_interval=POLL_S
    )
    dispenser.set_fault_listener(faults.append)
    await dispenser.connect()
    yield dispenser
    await dispenser.close()


async def test_implements_the_glue_dispenser_protocol(glue: ModbusGlueDispenser) -> None:
    assert isinstance(glue, GlueDispenser)
    assert glue.health.connected
    assert glue.health.last_rtt_ms is not None


async def test_setpoints_are_written_and_read_back(
    glue: ModbusGlueDispenser, sim: GlueSimulator
) -> None:
    await glue.set_flow_rate(123.4)
    await glue.set_pressure(45.6)
    status = await glue.read_status()
    assert status.flow_setpoint_ml_min == pytest.approx(123.4)
    assert status.pressure_setpoint_psi == pytest.approx(45.6)
    assert await sim.read_register(regs.FLOW_SETPOINT) == 1234
    assert await sim.read_register(regs.PRESSURE_SETPOINT) == 456


async def test_out_of_range_setpoint_is_refused_before_sending(
    glue: ModbusGlueDispenser, sim: GlueSimulator
) -> None:
    with pytest.raises(ValueError, match="FLOW_SETPOINT must be between 0 and 1000"):
        await glue.set_flow_rate(2000.0)
    assert await sim.read_register(regs.FLOW_SETPOINT) == 0


async def test_open_valve_flow_rises_close_valve_feedback_closed(
    glue: ModbusGlueDispenser, sim: GlueSimulator
) -> None:
    await glue.set_flow_rate(200.0)
    await glue.set_pressure(40.0)
    assert (await glue.read_status()).flow_ml_min == 0.0
    await glue.set_valve(True)
    assert sim.valve_open

    readings: list[float] = []

    async def flow_near_setpoint() -> None:
        while True:
            status = await glue.read_status()
            readings.append(status.flow_ml_min)
            if status.flow_ml_min > 190.0:
                return
            await asyncio.sleep(0.01)

    async with asyncio.timeout(5):
        await flow_near_setpoint()
    assert (await glue.read_status()).valve_open
    assert glue.health.details["valve_open"] is True

    await glue.set_valve(False)
    assert not sim.valve_open
    assert await sim.read_register(regs.VALVE_STATE) == 0
    assert sim.valve_closed_at is not None and sim.valve_closed_at <= time.time()
    status = await glue.read_status()
    assert not status.valve_open
    assert status.flow_ml_min == 0.0


async def test_no_reply_times_out_reports_once_then_recovers(
    glue: ModbusGlueDispenser, sim: GlueSimulator, faults: list[DeviceFault]
) -> None:
    sim.inject_no_reply()
    started = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"no reply within 0\.5 s") as caught:
        async with asyncio.timeout(TIMEOUT + 2.0):  # a hang fails here, not in CI's timeout
            await glue.read_status()
    assert time.monotonic() - started < TIMEOUT + 0.5, "the call must end near its timeout"
    assert caught.value.device == "glue"
    assert not glue.health.connected
    assert "no reply" in (glue.health.last_error or "")

    await asyncio.sleep(3 * TIMEOUT)  # several monitor polls also time out meanwhile
    assert len(codes(faults, "NO_REPLY")) == 1
    assert sim.dropped_requests >= 2

    sim.clear_faults()
    status = await glue.read_status()
    assert not status.valve_open
    assert glue.health.connected
    assert len(codes(faults, "NO_REPLY")) == 1

    sim.inject_no_reply()  # a new outage is a new onset
    await wait_until(lambda: len(codes(faults, "NO_REPLY")) == 2)
    sim.clear_faults()
    await wait_until(lambda: glue.health.connected)


async def test_no_reply_for_a_duration_clears_by_itself(
    glue: ModbusGlueDispenser, sim: GlueSimulator, faults: list[DeviceFault]
) -> None:
    sim.inject_no_reply(seconds=0.3)
    await wait_until(lambda: bool(codes(faults, "NO_REPLY")))
    await wait_until(lambda: glue.health.connected)
    await glue.set_flow_rate(10.0)


async def test_valve_close_during_silence_times_out(
    glue: ModbusGlueDispenser, sim: GlueSimulator
) -> None:
    await glue.set_valve(True)
    sim.inject_no_reply()
    with pytest.raises(DeviceTimeout, match="close valve"):
        async with asyncio.timeout(TIMEOUT + 2.0):
            await glue.set_valve(False)
    sim.clear_faults()
    await glue.set_valve(False)
    assert not sim.valve_open


async def test_alarm_bit_is_reported_once_naming_the_alarm(
    glue: ModbusGlueDispenser, sim: GlueSimulator, faults: list[DeviceFault]
) -> None:
    sim.set_alarm("NOZZLE_BLOCKED")
    await wait_until(lambda: bool(codes(faults, "ALARM")))
    await asyncio.sleep(5 * POLL_S)  # more polls see the same bit
    (alarm,) = codes(faults, "ALARM")
    assert alarm.device == "glue"
    assert alarm.message.startswith("glue dispenser alarm: NOZZLE_BLOCKED")
    assert glue.health.details["alarms"] == ["NOZZLE_BLOCKED"]
    assert (await glue.read_status()).alarms == ("NOZZLE_BLOCKED",)

    sim.set_alarm("RESERVOIR_LOW")  # only the new bit is news
    await wait_until(lambda: len(codes(faults, "ALARM")) == 2)
    assert "RESERVOIR_LOW" in faults[-1].message
    assert "NOZZLE_BLOCKED" not in faults[-1].message

    sim.clear_faults()
    await wait_until(lambda: glue.health.details["alarms"] == [])
    sim.set_alarm("NOZZLE_BLOCKED")  # it came back: a new onset
    await wait_until(lambda: len(codes(faults, "ALARM")) == 3)


async def test_pressure_out_of_range_is_reported_once(
    glue: ModbusGlueDispenser, sim: GlueSimulator, faults: list[DeviceFault]
) -> None:
    sim.force_pressure(200.0)
    await wait_until(lambda: bool(codes(faults, "PRESSURE_OUT_OF_RANGE")))
    await asyncio.sleep(5 * POLL_S)
    (fault,) = codes(faults, "PRESSURE_OUT_OF_RANGE")
    assert "200 PSI" in fault.message and "0-150 PSI" in fault.message
    assert glue.health.details["pressure_psi"] == pytest.approx(200.0)

    sim.force_pressure(None)
    await wait_until(lambda: glue.health.details["pressure_psi"] < 150.0)
    sim.force_pressure(180.0)
    await wait_until(lambda: len(codes(faults, "PRESSURE_OUT_OF_RANGE")) == 2)


async def test_exception_response_names_the_register(
    glue: ModbusGlueDispenser, sim: GlueSimulator
) -> None:
    sim.inject_exception(4)
    with pytest.raises(
        DeviceError, match=r"FLOW_SETPOINT \(holding register 1\).*exception 4"
    ) as e:
        await glue.set_flow_rate(10.0)
    assert not isinstance(e.value, DeviceTimeout)
    assert glue.health.connected, "the dispenser answered: the link is up"
    sim.clear_faults()
    await glue.set_flow_rate(10.0)


async def test_stuck_valve_fails_the_close_read_back(
    sim: GlueSimulator, faults: list[DeviceFault]
) -> None:
    # What is tested is the read-back, not the reply's time: a timeout the rest of a
    # full run cannot reach (TIMEOUT's 0.5 s was, once, the test process stalled).
    glue = ModbusGlueDispenser.tcp("127.0.0.1", sim.port, timeout=10.0, poll_interval=POLL_S)
    glue.set_fault_listener(faults.append)
    await glue.connect()
    try:
        await glue.set_valve(True)
        sim.inject_stuck_valve()
        with pytest.raises(DeviceError, match=r"VALVE_STATE .* still reports open"):
            await glue.set_valve(False)
        assert len(codes(faults, "VALVE_STUCK_OPEN")) == 1
        sim.clear_faults()
        await glue.set_valve(False)
        assert not sim.valve_open
    finally:
        await glue.close()


async def test_concurrent_calls_share_the_line(glue: ModbusGlueDispenser) -> None:
    calls = [glue.read_status() for _ in range(10)]
    calls += [glue.set_flow_rate(float(i)) for i in range(10)]
    calls.append(glue.set_valve(False))
    await asyncio.gather(*calls)
    assert glue.health.connected


async def test_line_arbiter_serves_valve_close_before_queued_work() -> None:
    arbiter = LineArbiter()
    order: list[str] = []

    async def use(name: str, priority: int) -> None:
        await arbiter.acquire(priority)
        order.append(name)
        await asyncio.sleep(0)
        arbiter.release()

    await arbiter.acquire(COMMAND)  # an exchange is on the wire
    tasks = [
        asyncio.create_task(use("poll", POLL)),
        asyncio.create_task(use("flow", COMMAND)),
        asyncio.create_task(use("close", URGENT)),
    ]
    cancelled = asyncio.create_task(use("gave-up", COMMAND))
    await asyncio.sleep(0.01)
    cancelled.cancel()
    arbiter.release()
    await asyncio.gather(*tasks)
    assert order == ["close", "flow", "poll"]
    await asyncio.wait_for(arbiter.acquire(POLL), 1.0)  # nothing leaked


async def test_line_arbiter_drops_waiting_openings_and_serves_the_rest() -> None:
    arbiter = LineArbiter()
    order: list[str] = []

    async def use(name: str, priority: int, droppable: bool = False) -> None:
        await arbiter.acquire(priority, droppable=droppable)
        order.append(name)
        arbiter.release()

    await arbiter.acquire(COMMAND)  # an exchange is on the wire
    opening = asyncio.create_task(use("open", COMMAND, droppable=True))
    flow = asyncio.create_task(use("flow", COMMAND))
    await asyncio.sleep(0.01)
    assert arbiter.drop_waiting() == 1
    close = asyncio.create_task(use("close", URGENT))
    await asyncio.sleep(0.01)
    arbiter.release()
    await asyncio.gather(flow, close)
    with pytest.raises(asyncio.CancelledError):
        await opening
    assert order == ["close", "flow"]
    assert arbiter.drop_waiting() == 0  # nothing left to drop
    await asyncio.wait_for(arbiter.acquire(POLL), 1.0)  # nothing leaked


async def test_wrong_device_id_gets_no_reply(sim: GlueSimulator) -> None:
    dispenser = ModbusGlueDispenser.tcp("127.0.0.1", sim.port, device_id=2, timeout=0.3)
    with pytest.raises(DeviceTimeout, match="from device 2"):
        await dispenser.connect()
    assert sim.dropped_requests >= 1
    await dispenser.close()


async def test_refused_connection_is_device_disconnected() -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    dispenser = ModbusGlueDispenser.tcp("127.0.0.1", port, timeout=TIMEOUT)
    with pytest.raises(DeviceDisconnected, match=f"127.0.0.1:{port}"):
        async with asyncio.timeout(5):
            await dispenser.connect()
    assert not dispenser.health.connected
    await dispenser.close()


async def test_simulator_gone_is_reported_once(
    glue: ModbusGlueDispenser, sim: GlueSimulator, faults: list[DeviceFault]
) -> None:
    await sim.stop()
    await wait_until(lambda: not glue.health.connected)
    await asyncio.sleep(3 * TIMEOUT)
    link_faults = [f for f in faults if f.code in ("COMM_LOST", "NO_REPLY")]
    assert len(link_faults) == 1
    with pytest.raises(DeviceError):
        await glue.read_status()


async def test_serial_port_that_does_not_exist_fails_clearly() -> None:
    dispenser = ModbusGlueDispenser.serial("/dev/ttyNOPE", timeout=TIMEOUT)
    with pytest.raises(DeviceError, match="/dev/ttyNOPE"):
        async with asyncio.timeout(5):
            await dispenser.connect()
    await dispenser.close()


async def test_close_is_idempotent_and_calls_after_close_fail(glue: ModbusGlueDispenser) -> None:
    await glue.close()
    await glue.close()
    assert not glue.health.connected
    with pytest.raises(DeviceDisconnected, match="call connect"):
        await glue.read_status()


async def _control(
    reader: asyncio.StreamReader, writer: asyncio.StreamWriter, request: dict[str, object]
) -> dict[str, object]:
    writer.write(json.dumps(request).encode() + b"\n")
    await writer.drain()
    reply: dict[str, object] = json.loads(await reader.readline())
    return reply


async def test_simulator_as_a_separate_process() -> None:
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "server.drivers.sim.glue_sim",
        "--host",
        "127.0.0.1",
        "--port",
        "0",
        "--control-port",
        "0",
        cwd=ROOT,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    assert proc.stdout is not None and proc.stderr is not None
    faults: list[DeviceFault] = []
    try:
        port = control_port = None
        async with asyncio.timeout(15):
            while port is None:
                line = (await proc.stdout.readline()).decode()
                if not line:
                    pytest.fail(f"simulator exited: {(await proc.stderr.read()).decode()}")
                if m := re.fullmatch(r"glue simulator control on 127\.0\.0\.1:(\d+)\n", line):
                    control_port = int(m.group(1))
                if m := re.fullmatch(r"glue simulator listening on 127\.0\.0\.1:(\d+)\n", line):
                    port = int(m.group(1))
        assert control_port is not None

        glue = ModbusGlueDispenser.tcp("127.0.0.1", port, timeout=TIMEOUT, poll_interval=POLL_S)
        glue.set_fault_listener(faults.append)
        await glue.connect()
        status = await glue.read_status()
        assert not status.valve_open and status.alarms == ()

        reader, writer = await asyncio.open_connection("127.0.0.1", control_port)
        reply = await _control(reader, writer, {"cmd": "alarm", "name": "RESERVOIR_LOW"})
        assert reply["ok"] is True
        assert (await glue.read_status()).alarms == ("RESERVOIR_LOW",)
        await wait_until(lambda: bool(codes(faults, "ALARM")))
        assert "RESERVOIR_LOW" in codes(faults, "ALARM")[0].message

        reply = await _control(reader, writer, {"cmd": "melt"})
        assert reply["ok"] is False and "unknown cmd" in str(reply["error"])

        assert (await _control(reader, writer, {"cmd": "no_reply"}))["ok"] is True
        with pytest.raises(DeviceTimeout):
            await glue.read_status()
        assert (await _control(reader, writer, {"cmd": "clear"}))["ok"] is True
        assert (await glue.read_status()).alarms == ()
        writer.close()

        proc.send_signal(signal.SIGTERM)  # with the driver still connected
        async with asyncio.timeout(10):
            assert await proc.wait() == 0
        await glue.close()
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


async def test_an_exchange_from_before_a_new_session_cannot_fault_it(
    glue: ModbusGlueDispenser, sim: GlueSimulator, faults: list[DeviceFault]
) -> None:
    sim.inject_no_reply()
    stale = asyncio.create_task(glue.read_status())  # asked during the silence
    await asyncio.sleep(0)
    glue.new_session()  # what a reset's probe does first
    sim.clear_faults()
    with contextlib.suppress(DeviceTimeout):
        await stale
    await asyncio.sleep(3 * TIMEOUT)  # the swallowed exchanges of the old session have ended
    assert codes(faults, "NO_REPLY") == []
    status = await glue.read_status()
    assert not status.valve_open and glue.health.connected


# --- supervision: flow, pressure while spraying, temperature, silence with the valve open ---


async def supervised(
    sim: GlueSimulator, faults: list[DeviceFault], **options
) -> ModbusGlueDispenser:
    """A dispenser with the cell's supervision switched on (options override)."""
    settings = {
        "timeout": TIMEOUT,
        "poll_interval": POLL_S,
        "pressure_range_psi": (20.0, 60.0),
        "flow_tolerance_pct": 20.0,
        "flow_deviation_s": 0.3,
        "temperature_range_c": (10.0, 40.0),
        "link_timeout": 0.25,
        **options,
    }
    dispenser = ModbusGlueDispenser.tcp("127.0.0.1", sim.port, **settings)
    dispenser.set_fault_listener(faults.append)
    await dispenser.connect()
    return dispenser


async def spray(glue: ModbusGlueDispenser, flow: float = 100.0, psi: float = 40.0) -> None:
    await glue.set_flow_rate(flow)
    await glue.set_pressure(psi)
    await glue.set_valve(True)
    await wait_until(lambda: glue.health.details["flow_ml_min"] > 0.9 * flow)


async def test_normal_spraying_trips_no_supervision(
    sim: GlueSimulator, faults: list[DeviceFault]
) -> None:
    """At rest (pressure setpoint 0, below the window's low end) and while spraying."""
    glue = await supervised(sim, faults)
    try:
        await asyncio.sleep(10 * POLL_S)  # at rest: the low pressure limit does not apply
        await spray(glue)
        await asyncio.sleep(0.5)  # longer than flow_deviation_s, many polls
        await glue.set_flow_rate(50.0)  # a setpoint change while spraying settles in time
        await asyncio.sleep(0.5)
        await glue.set_valve(False)
        assert faults == []
        assert glue.health.active_faults == ()
    finally:
        await glue.close()


async def test_flow_off_its_setpoint_while_spraying_is_reported_once(
    sim: GlueSimulator, faults: list[DeviceFault]
) -> None:
    glue = await supervised(sim, faults)
    try:
        sim.force_flow(40.0)  # pinned only while the valve is open: at rest nothing to see
        await asyncio.sleep(10 * POLL_S)
        assert codes(faults, "FLOW_DEVIATION") == []
        await glue.set_flow_rate(100.0)
        await glue.set_pressure(40.0)
        await glue.set_valve(True)
        await wait_until(lambda: bool(codes(faults, "FLOW_DEVIATION")))
        await asyncio.sleep(5 * POLL_S)
        (fault,) = codes(faults, "FLOW_DEVIATION")
        assert "40 ml/min is 60 % off its setpoint 100 ml/min (allowed 20 %)" in fault.message
        assert any("flow" in f for f in glue.health.active_faults)
        await glue.set_valve(False)  # no longer spraying: the condition is gone
        await wait_until(lambda: glue.health.active_faults == ())
    finally:
        await glue.close()


async def test_low_pressure_is_a_fault_only_while_spraying(
    sim: GlueSimulator, faults: list[DeviceFault]
) -> None:
    glue = await supervised(sim, faults)
    try:
        sim.force_pressure(5.0)
        await asyncio.sleep(10 * POLL_S)
        assert codes(faults, "PRESSURE_OUT_OF_RANGE") == []  # a supply at rest
        await glue.set_valve(True)
        await wait_until(lambda: bool(codes(faults, "PRESSURE_OUT_OF_RANGE")))
        (fault,) = codes(faults, "PRESSURE_OUT_OF_RANGE")
        assert "5 PSI is outside the allowed 20-60 PSI while spraying" in fault.message
        await glue.set_valve(False)
        sim.force_pressure(70.0)  # above the window: a fault whatever the valve does
        await wait_until(lambda: len(codes(faults, "PRESSURE_OUT_OF_RANGE")) == 2)
    finally:
        await glue.close()


async def test_temperature_outside_its_window_is_reported_once(
    sim: GlueSimulator, faults: list[DeviceFault]
) -> None:
    glue = await supervised(sim, faults)
    try:
        sim.force_temperature(55.0)
        await wait_until(lambda: bool(codes(faults, "TEMPERATURE_OUT_OF_RANGE")))
        await asyncio.sleep(5 * POLL_S)
        (fault,) = codes(faults, "TEMPERATURE_OUT_OF_RANGE")
        assert "55 °C is outside the allowed 10-40 °C" in fault.message
        assert glue.health.active_faults == ("glue: temperature 55.0 °C outside 10..40 °C",)
        sim.force_temperature(None)
        await wait_until(lambda: glue.health.active_faults == ())
        sim.force_temperature(2.0)
        await wait_until(lambda: len(codes(faults, "TEMPERATURE_OUT_OF_RANGE")) == 2)
    finally:
        await glue.close()


async def test_silence_with_the_valve_open_is_a_fault_within_the_link_timeout(
    sim: GlueSimulator, faults: list[DeviceFault]
) -> None:
    """Not after the (here 30 s) exchange timeout: the valve could not be confirmed closed."""
    glue = await supervised(sim, faults, timeout=30.0)
    try:
        await spray(glue)
        sim.inject_no_reply()
        await wait_until(lambda: bool(codes(faults, "VALVE_UNCONFIRMED")), within=10.0)
        (fault,) = codes(faults, "VALVE_UNCONFIRMED")
        assert "the valve could not be confirmed closed" in fault.message
        assert "link timeout 0.25 s" in fault.message
        assert not glue.health.connected
        # The silent exchange was ended: a close is sent now, not after 30 s, and is
        # itself bounded by the link timeout while the dispenser stays silent.
        with pytest.raises(DeviceTimeout, match="link timeout"):
            async with asyncio.timeout(10.0):
                await glue.set_valve(False)
        assert codes(faults, "NO_REPLY") == []  # one report per outage
        sim.clear_faults()
        await glue.set_valve(False)  # answered: read back closed, supervision at rest
        assert not sim.valve_open
        assert glue.health.connected
        sim.inject_no_reply()  # silence with the valve closed is no valve fault
        await asyncio.sleep(4 * 0.25)
        assert len(codes(faults, "VALVE_UNCONFIRMED")) == 1
    finally:
        await glue.close()


async def test_a_close_read_back_shows_in_health_before_the_next_poll(
    sim: GlueSimulator, faults: list[DeviceFault]
) -> None:
    glue = await supervised(sim, faults, poll_interval=60.0, link_timeout=None)
    try:
        await glue.set_valve(True)
        await glue.read_status()
        assert glue.health.details["valve_open"] is True
        before = glue.health.details["status_at"]
        await glue.set_valve(False)
        assert glue.health.details["valve_open"] is False
        assert glue.health.details["status_at"] >= before
    finally:
        await glue.close()


def test_a_link_timeout_must_exceed_the_poll_interval() -> None:
    with pytest.raises(ValueError, match=r"link_timeout .* must be longer than poll_interval"):
        ModbusGlueDispenser.tcp("127.0.0.1", 1, poll_interval=0.5, link_timeout=0.5)


@pytest.mark.parametrize("turns", range(2))
async def test_a_cancel_landing_as_the_reply_arrives_still_cancels(
    sim: GlueSimulator, turns: int
) -> None:
    """The e-stop cancels a run while its valve or setpoint write is on the line.

    pymodbus bounds each exchange with asyncio.wait_for, which on Python 3.11
    drops a cancellation that lands in the loop turns between the reply's
    arrival and wait_for returning (CPython gh-86296). Before the fix the
    write then returned normally and the cancelled run went on (its next move
    started after the stop), and the worker waited emergency_stop_timeout for it.
    """
    dispenser = ModbusGlueDispenser.tcp("127.0.0.1", sim.port, timeout=TIMEOUT, poll_interval=30)
    await dispenser.connect()
    try:
        assert dispenser._client is not None
        exchange = dispenser._client.ctx  # pymodbus's transaction manager: the reply's future
        task = asyncio.ensure_future(dispenser.set_flow_rate(100.0))
        while not (dispenser._waiting_since and exchange.response_future.done()):
            await asyncio.sleep(0)  # the reply has landed; wait_for has not returned yet
        for _ in range(turns):
            await asyncio.sleep(0)
        assert not task.done()
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
    finally:
        await dispenser.close()
