"""The production robot client against the network simulator, over real loopback sockets.

Motion runs `SPEED_FACTOR` times faster than commanded so the suite takes
seconds; timeouts are functional bounds sized for a loaded 2-core machine,
never performance assertions.
"""

from __future__ import annotations

import asyncio
import gc
import itertools
import json
import math
import os
import re
import signal
import socket
import sys
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest

from server.common.errors import DeviceDisconnected, DeviceTimeout, RobotCommandError
from server.drivers.base import DeviceFault, Pose, Robot
from server.drivers.jsonlines import encode_message, make_request, make_result
from server.drivers.robot_jsonrpc import JsonRpcRobot, MotionInterrupted
from server.drivers.sim.robot_sim import RobotSimulator

SPEED_FACTOR = 20.0
TIMEOUT = 3.0  # robot_communication_timeout for most tests
HOME = Pose(400.0, 0.0, 200.0, 180.0, 0.0, 0.0)
FAR = Pose(700.0, 300.0, 50.0, 180.0, 0.0, 0.0)  # ~522 mm from HOME
SLOW = 10.0  # mm/s: FAR takes ~2.6 s at SPEED_FACTOR, long enough to act mid-move
REPO_ROOT = Path(__file__).resolve().parents[2]


async def wait_until(
    condition: Callable[[], bool | Awaitable[bool]], timeout: float = 10.0, what: str = ""
) -> None:
    """Poll until `condition` holds; fail the test after `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if not isinstance(value, bool):
            value = await value
        if value:
            return
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what or condition}")
        await asyncio.sleep(0.01)


def close_to(a: Pose, b: Pose, tolerance: float = 1e-6) -> bool:
    return all(math.isclose(x, y, abs_tol=tolerance) for x, y in zip(a, b, strict=True))


@pytest.fixture
async def sim() -> AsyncIterator[RobotSimulator]:
    simulator = RobotSimulator(speed_factor=SPEED_FACTOR)
    await simulator.start()
    yield simulator
    await simulator.stop()


def make_robot(port: int, timeout: float = TIMEOUT) -> JsonRpcRobot:
    return JsonRpcRobot(
        "127.0.0.1",
        port,
        timeout=timeout,
        reconnect_initial_delay=0.05,
        reconnect_max_delay=0.5,
    )


@pytest.fixture
async def robot(sim: RobotSimulator) -> AsyncIterator[JsonRpcRobot]:
    client = make_robot(sim.port)
    await client.connect()
    yield client
    await client.close()


# --- motion -------------------------------------------------------------------


async def test_client_satisfies_the_robot_protocol(robot: JsonRpcRobot) -> None:
    assert isinstance(robot, Robot)
    assert robot.health.connected
    assert robot.health.last_rtt_ms is not None
    assert await robot.get_position() == HOME


async def test_move_linear_reaches_the_pose(robot: JsonRpcRobot, sim: RobotSimulator) -> None:
    target = Pose(500.0, -100.0, 120.0, 180.0, 0.0, 90.0)
    await robot.move_linear(target, 400.0, 2000.0)
    assert close_to(await robot.get_position(), target)
    assert close_to(sim.position, target)
    assert not await robot.is_moving()


async def test_move_joint_reaches_the_pose(robot: JsonRpcRobot, sim: RobotSimulator) -> None:
    target = Pose(300.0, 200.0, 300.0, 170.0, 10.0, -45.0)
    await robot.move_joint(target, 300.0)
    assert close_to(await robot.get_position(), target)
    assert sim.executed_path[-1].method == "moveJ"


async def test_is_moving_is_true_during_motion(robot: JsonRpcRobot, sim: RobotSimulator) -> None:
    move = asyncio.create_task(robot.move_linear(FAR, SLOW, 1000.0))
    await wait_until(robot.is_moving, what="isMoving to turn true")
    moving_at = await robot.get_position()
    assert moving_at != HOME and moving_at != FAR  # interpolated on the way
    await asyncio.wait_for(move, 20)
    assert not await robot.is_moving()
    assert close_to(await robot.get_position(), FAR)


@pytest.mark.parametrize(
    ("pose", "axis", "limit"),
    [
        (Pose(900.0, 0.0, 200.0), "x", "800"),
        (Pose(400.0, -450.0, 200.0), "y", "-400"),
        (Pose(400.0, 0.0, -10.0), "z", "-5"),
    ],
)
async def test_workspace_violation_is_refused_and_nothing_moves(
    robot: JsonRpcRobot, sim: RobotSimulator, pose: Pose, axis: str, limit: str
) -> None:
    with pytest.raises(RobotCommandError) as caught:
        await robot.move_linear(pose, 100.0, 1000.0)
    assert caught.value.code == 1001
    assert caught.value.method == "moveL"
    assert f"{axis}=" in str(caught.value) and limit in str(caught.value)
    assert not sim.is_moving
    assert sim.executed_path == []
    assert await robot.get_position() == HOME


async def test_stop_during_a_move_halts_it(robot: JsonRpcRobot, sim: RobotSimulator) -> None:
    move = asyncio.create_task(robot.move_linear(FAR, SLOW, 1000.0))
    await wait_until(lambda: sim.is_moving, what="the simulated arm to move")
    await robot.stop()  # pipelined on the same connection while move_linear polls
    with pytest.raises(MotionInterrupted):
        await asyncio.wait_for(move, 10)
    reached = await robot.get_position()
    assert math.dist(reached[:3], FAR[:3]) > 1.0
    assert not await robot.is_moving()
    (segment,) = sim.executed_path
    assert segment.interrupted
    assert close_to(segment.end, reached)
    assert sim.stop_received_count == 1


async def test_cancelling_the_move_sends_stop(robot: JsonRpcRobot, sim: RobotSimulator) -> None:
    move = asyncio.create_task(robot.move_linear(FAR, SLOW, 1000.0))
    await wait_until(lambda: sim.is_moving, what="the simulated arm to move")
    before = time.time()
    move.cancel()
    with pytest.raises(asyncio.CancelledError):
        await move
    # The stop is awaited (shielded) before CancelledError comes out.
    assert sim.stop_received_count == 1
    assert sim.last_stop_at is not None and sim.last_stop_at >= before - 1.0
    assert not sim.is_moving
    assert sim.executed_path[-1].interrupted
    assert math.dist(sim.position[:3], FAR[:3]) > 1.0


async def test_executed_path_matches_the_commanded_waypoints(
    robot: JsonRpcRobot, sim: RobotSimulator
) -> None:
    waypoints = [
        (Pose(300.0, -100.0, 20.0), 500.0),
        (Pose(500.0, -100.0, 20.0), 250.0),
        (Pose(500.0, 100.0, 20.0), 250.0),
        (Pose(300.0, 100.0, 20.0), 300.0),
    ]
    for pose, speed in waypoints:
        await robot.move_linear(pose, speed, 2000.0)
    path = sim.executed_path
    assert len(path) == len(waypoints)
    start = HOME
    for segment, (pose, speed) in zip(path, waypoints, strict=True):
        assert close_to(segment.start, start)
        assert close_to(segment.end, pose)
        assert segment.speed == speed
        assert not segment.interrupted
        assert segment.t_start <= segment.t_end
        start = pose
    assert all(a.t_end <= b.t_start + 1e-3 for a, b in itertools.pairwise(path))
    over_the_wire = await robot.call("sim.getExecutedPath")
    assert [s["end"] for s in over_the_wire] == [list(p) for p, _ in waypoints]
    assert await robot.call("sim.clearPath") is True
    assert sim.executed_path == []


async def test_a_new_move_replaces_the_current_one(
    robot: JsonRpcRobot, sim: RobotSimulator
) -> None:
    assert await robot.call("moveL", [list(FAR), SLOW, 1000.0]) is True
    await wait_until(lambda: sim.is_moving)
    second = Pose(300.0, -200.0, 100.0)
    assert await robot.call("moveL", {"pose": list(second), "speed": 500.0, "acceleration": 1e3})
    await wait_until(lambda: not sim.is_moving, what="the second move to finish")
    first, replacement = sim.executed_path
    assert first.interrupted and not replacement.interrupted
    assert close_to(replacement.start, first.end)
    assert close_to(replacement.end, second)


@pytest.mark.parametrize(
    "params",
    [
        [[400, 0, 200, 180, 0], 10, 100],  # 5 values
        [[400, 0, 200, 180, 0, 0], "fast", 100],
        [[400, 0, 200, 180, 0, 0], -5, 100],
        [[400, 0, 200, 180, 0, 0], 10],
        {"pose": [400, 0, 200, 180, 0, 0], "speed": 10},
        {"pose": [400, 0, 200, 180, 0, 0], "speed": 10, "acceleration": 1, "blend": 2},
        [[400, 0, 200, True, 0, 0], 10, 100],
    ],
)
async def test_bad_params_are_refused(robot: JsonRpcRobot, params: Any) -> None:
    with pytest.raises(RobotCommandError) as caught:
        await robot.call("moveL", params)
    assert caught.value.code == -32602


async def test_unknown_method_is_refused(robot: JsonRpcRobot) -> None:
    with pytest.raises(RobotCommandError) as caught:
        await robot.call("moveCircular", [])
    assert caught.value.code == -32601


# --- fault injection ------------------------------------------------------------


async def test_drop_fails_the_pending_call_at_once_and_the_client_reconnects(
    sim: RobotSimulator,
) -> None:
    robot = make_robot(sim.port, timeout=30.0)  # a DeviceTimeout would take 30 s
    faults: list[DeviceFault] = []
    robot.set_fault_listener(faults.append)
    await robot.connect()
    try:
        sim.inject_fault("stall")  # keeps the next call pending
        asked = sim.method_counts["getPosition"]
        pending = asyncio.create_task(robot.get_position())
        await wait_until(lambda: sim.method_counts["getPosition"] > asked)
        sim.clear_faults()
        sim.inject_fault("drop", duration=0.3)  # and refuse reconnections for a while
        with pytest.raises(DeviceDisconnected):
            await asyncio.wait_for(pending, 10)
        assert not robot.health.connected
        with pytest.raises(DeviceDisconnected):  # fail fast, no queueing
            await asyncio.wait_for(robot.stop(), 1.0)
        await wait_until(lambda: robot.health.connected, what="the background reconnection")
        assert await robot.get_position() == HOME
        assert [f.code for f in faults] == ["COMM_LOST"]  # once, despite refused retries
        assert faults[0].device == "robot"
        assert robot.health.details["connection_losses"] == 1
        assert robot.health.details["reconnects"] == 1
    finally:
        await robot.close()


async def test_a_stop_goes_out_through_a_stall_with_requests_pending(
    robot: JsonRpcRobot, sim: RobotSimulator
) -> None:
    """A stalled controller swallows requests; the stop still reaches its socket at once.

    The driver pipelines: nothing pending (polls, a heartbeat) holds the stop back,
    so the halt's stop is on the wire before its own timeout starts to matter.
    """
    sim.inject_fault("stall")
    pending = [asyncio.create_task(robot.get_position()) for _ in range(20)]
    await wait_until(lambda: sim.ignored_while_stalled == 20, what="the requests swallowed")
    stopping = asyncio.create_task(robot.stop())
    await wait_until(lambda: sim.stop_received_count == 1, what="the stop received")
    sim.clear_faults()
    for task in [*pending, stopping]:
        task.cancel()
    await asyncio.gather(*pending, stopping, return_exceptions=True)


async def test_a_stop_goes_out_on_a_link_whose_probe_has_not_answered(
    sim: RobotSimulator,
) -> None:
    """Other calls wait for the connection probe; a stop is written on the new socket."""
    robot = make_robot(sim.port, timeout=30.0)  # the probe stays pending for the whole test
    await robot.connect()
    try:
        sim.inject_fault("stall")  # the reconnection's probe will be swallowed
        sim.inject_fault("drop")
        await wait_until(lambda: not robot.connected, what="the link lost")
        await wait_until(lambda: sim.ignored_while_stalled >= 1, what="the probe swallowed")
        assert not robot.connected  # still probing
        with pytest.raises(DeviceDisconnected):  # an ordinary call waits for the probe
            await robot.get_position()
        stopping = asyncio.create_task(robot.stop())
        await wait_until(lambda: sim.stop_received_count == 1, what="the stop on the new link")
        stopping.cancel()  # swallowed by the stall like the probe: never answered
        await asyncio.gather(stopping, return_exceptions=True)
    finally:
        sim.clear_faults()
        await robot.close()


async def test_a_stop_that_found_no_link_is_sent_first_on_the_next(sim: RobotSimulator) -> None:
    robot = make_robot(sim.port)
    await robot.connect()
    try:
        sim.inject_fault("drop", duration=0.5)  # and refuse reconnections for a while
        await wait_until(lambda: not robot.connected, what="the link lost")
        asked = sim.method_counts["getPosition"]
        with pytest.raises(DeviceDisconnected):  # no link (or one refused under it)
            await robot.stop()
        assert sim.stop_received_count == 0
        await wait_until(lambda: robot.connected, what="the background reconnection")
        assert sim.stop_received_count == 1
        # Sent before the probe: the probe's getPosition was answered after the stop.
        assert sim.method_counts["getPosition"] > asked
        await robot.get_position()
        assert sim.stop_received_count == 1  # owed once, sent once
    finally:
        await robot.close()


async def test_drop_during_a_move_fails_the_move(sim: RobotSimulator) -> None:
    robot = make_robot(sim.port)
    faults: list[DeviceFault] = []
    robot.set_fault_listener(faults.append)
    await robot.connect()
    try:
        move = asyncio.create_task(robot.move_linear(FAR, SLOW, 1000.0))
        await wait_until(lambda: sim.is_moving)
        assert await robot.call("sim.injectFault", {"kind": "drop"}) is True  # answered, then drop
        with pytest.raises(DeviceDisconnected):
            await asyncio.wait_for(move, 10)
        await wait_until(lambda: robot.health.connected, what="the background reconnection")
        assert len(faults) == 1
    finally:
        await robot.close()


async def test_stall_gives_device_timeout(sim: RobotSimulator) -> None:
    robot = make_robot(sim.port, timeout=0.3)
    await robot.connect()
    try:
        assert await robot.call("sim.injectFault", [{"kind": "stall"}]) is True
        started = time.monotonic()
        with pytest.raises(DeviceTimeout):
            await robot.get_position()
        assert time.monotonic() - started >= 0.3
        with pytest.raises(DeviceTimeout):
            await robot.move_linear(FAR, 100.0, 1000.0)
        with pytest.raises(DeviceTimeout):
            await robot.stop()  # a stalled controller ignores stop too
        stats = await robot.call("sim.stats")  # sim.* is exempt from the stall
        assert stats["stalled"] and stats["ignored_while_stalled"] >= 3
        assert await robot.call("sim.clearFaults") is True
        assert robot.health.connected  # a timeout is not a lost link
        assert await robot.get_position() == HOME
        assert "no answer" in (robot.health.last_error or "")
    finally:
        await robot.close()


async def test_the_heartbeat_finds_a_controller_that_stops_answering_while_idle(
    sim: RobotSimulator,
) -> None:
    robot = JsonRpcRobot("127.0.0.1", sim.port, timeout=0.3, heartbeat_interval=0.05)
    faults: list[DeviceFault] = []
    robot.set_fault_listener(faults.append)
    await robot.connect()
    try:
        await wait_until(lambda: "position" in robot.health.details, what="a heartbeat")
        assert robot.health.details["position"] == list(HOME)
        sim.inject_fault("stall")  # nothing else is asked of the robot meanwhile
        await wait_until(lambda: bool(faults), what="the silence reported")
        assert [f.code for f in faults] == ["NO_ANSWER"]
        assert "stopped answering" in faults[0].message
        assert robot.health.active_faults == ("robot: no answer within 0.3 s",)
        assert robot.health.connected  # silent, not disconnected: no reconnection storm
        await asyncio.sleep(0.8)  # silent for several more heartbeats: reported once
        assert len(faults) == 1
        sim.clear_faults()
        await wait_until(lambda: robot.health.active_faults == (), what="the fault cleared")
        assert robot.health.connected and len(faults) == 1
    finally:
        await robot.close()


async def test_no_heartbeat_unless_asked(robot: JsonRpcRobot, sim: RobotSimulator) -> None:
    before = (await robot.call("sim.stats"))["methods"].get("getPosition", 0)
    await asyncio.sleep(0.2)
    assert (await robot.call("sim.stats"))["methods"].get("getPosition", 0) == before


async def test_stall_with_duration_ends_by_itself(robot: JsonRpcRobot, sim: RobotSimulator) -> None:
    await robot.call("sim.injectFault", {"kind": "stall", "duration": 0.2})
    assert sim.stalled
    await asyncio.sleep(0.3)
    assert await robot.get_position() == HOME


async def test_fail_next_refuses_one_motion(robot: JsonRpcRobot, sim: RobotSimulator) -> None:
    await robot.call("sim.injectFault", {"kind": "fail_next"})
    assert await robot.get_position() == HOME  # non-motion commands are unaffected
    with pytest.raises(RobotCommandError) as caught:
        await robot.move_linear(Pose(500.0, 0.0, 100.0), 300.0, 1000.0)
    assert caught.value.code == 1002
    assert sim.executed_path == []
    await robot.move_linear(Pose(500.0, 0.0, 100.0), 300.0, 1000.0)
    assert close_to(await robot.get_position(), Pose(500.0, 0.0, 100.0))


async def test_bad_fault_kind_is_refused(robot: JsonRpcRobot) -> None:
    with pytest.raises(RobotCommandError) as caught:
        await robot.call("sim.injectFault", {"kind": "explode"})
    assert caught.value.code == -32602


async def test_stats_count_methods_and_stops(robot: JsonRpcRobot) -> None:
    await robot.stop()
    stats = await robot.call("sim.stats")
    assert stats["methods"]["stop"] == 1
    assert stats["stop_count"] == 1
    assert abs(stats["last_stop_at"] - time.time()) < 60
    assert stats["clients"] == 1


async def test_close_is_not_a_fault(sim: RobotSimulator) -> None:
    robot = make_robot(sim.port)
    faults: list[DeviceFault] = []
    robot.set_fault_listener(faults.append)
    await robot.connect()
    await robot.close()
    await asyncio.sleep(0.2)
    assert faults == []
    assert not robot.health.connected
    with pytest.raises(DeviceDisconnected):
        await robot.get_position()
    await wait_until(lambda: sim.client_count == 0)


async def test_connect_to_nothing_raises_disconnected() -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        free_port = probe.getsockname()[1]
    robot = make_robot(free_port)
    with pytest.raises(DeviceDisconnected):
        await robot.connect()
    assert not robot.health.connected
    await robot.close()


# --- raw sockets ----------------------------------------------------------------


@pytest.fixture
async def raw(
    sim: RobotSimulator,
) -> AsyncIterator[tuple[asyncio.StreamReader, asyncio.StreamWriter]]:
    reader, writer = await asyncio.open_connection("127.0.0.1", sim.port)
    yield reader, writer
    writer.close()


async def read_message(reader: asyncio.StreamReader) -> dict[str, Any]:
    line = await asyncio.wait_for(reader.readline(), 5)
    assert line.endswith(b"\n")
    return json.loads(line)


async def test_raw_request_split_across_writes(raw: Any) -> None:
    reader, writer = raw
    data = encode_message(make_request("getPosition", [], 1))
    writer.write(data[:10])
    await writer.drain()
    await asyncio.sleep(0.05)
    writer.write(data[10:])
    assert await read_message(reader) == make_result(1, list(HOME))


async def test_raw_split_inside_a_multibyte_character(raw: Any) -> None:
    reader, writer = raw
    data = encode_message(make_request("isMoving", [], "bead-°1"))
    cut = data.index("°".encode()) + 1
    writer.write(data[:cut])
    await writer.drain()
    await asyncio.sleep(0.05)
    writer.write(data[cut:])
    assert await read_message(reader) == make_result("bead-°1", False)


async def test_raw_merged_requests_get_answers_in_order(raw: Any) -> None:
    reader, writer = raw
    writer.write(
        encode_message(make_request("isMoving", [], 1))
        + encode_message(make_request("stop"))  # a notification: no answer
        + encode_message(make_request("getPosition", {}, 2))
    )
    assert (await read_message(reader))["id"] == 1
    assert await read_message(reader) == make_result(2, list(HOME))


async def test_raw_malformed_json_answers_parse_error_and_keeps_the_connection(
    raw: Any,
) -> None:
    reader, writer = raw
    writer.write(b'{"jsonrpc": "2.0", "method": \n')
    error = await read_message(reader)
    assert error["id"] is None and error["error"]["code"] == -32700
    writer.write(encode_message(make_request("getPosition", [], 5)))
    assert (await read_message(reader))["id"] == 5


async def test_raw_batch_and_invalid_requests_are_refused(raw: Any) -> None:
    reader, writer = raw
    writer.write(encode_message([make_request("getPosition", [], 1)]))
    assert (await read_message(reader))["error"]["code"] == -32600
    writer.write(encode_message({"method": "getPosition", "id": 2}))
    refused = await read_message(reader)
    assert refused["id"] == 2 and refused["error"]["code"] == -32600


async def test_unknown_ids_and_garbage_from_the_controller_are_ignored() -> None:
    """A tiny fake controller that precedes every answer with noise."""

    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while line := await reader.readline():
            request = json.loads(line)
            writer.write(encode_message(make_result(987654, "not yours")))
            writer.write(b"this is not json\n")
            writer.write(encode_message(make_result(request["id"], [1, 2, 3, 4, 5, 6])))
            await writer.drain()
        writer.close()

    server = await asyncio.start_server(serve, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    robot = make_robot(port)
    try:
        await robot.connect()  # the connection probe sees the noise too
        assert await robot.get_position() == Pose(1, 2, 3, 4, 5, 6)
        assert robot.health.details["unknown_responses"] == 2
        assert robot.health.details["malformed_lines"] == 2
        assert robot.health.connected
    finally:
        await robot.close()
        server.close()
        await server.wait_closed()


async def test_simulator_runs_as_a_separate_process() -> None:
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(REPO_ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "server.drivers.sim.robot_sim",
        "--port",
        "0",
        "--speed-factor",
        "50",
        cwd=REPO_ROOT,
        env=env,
        stdout=asyncio.subprocess.PIPE,
    )
    try:
        assert process.stdout is not None
        line = (await asyncio.wait_for(process.stdout.readline(), 30)).decode()
        match = re.fullmatch(r"robot simulator listening on 127\.0\.0\.1:(\d+)\s*", line)
        assert match, line
        robot = make_robot(int(match.group(1)))
        await robot.connect()
        assert await robot.get_position() == HOME
        await robot.move_linear(Pose(450.0, 0.0, 200.0), 500.0, 1000.0)
        await robot.close()
        process.send_signal(signal.SIGTERM)
        assert await asyncio.wait_for(process.wait(), 15) == 0
    finally:
        if process.returncode is None:
            process.kill()
            await process.wait()


async def test_a_request_from_before_a_new_session_cannot_fault_it(sim: RobotSimulator) -> None:
    robot = make_robot(sim.port, timeout=0.5)
    faults: list[DeviceFault] = []
    robot.set_fault_listener(faults.append)
    await robot.connect()
    try:
        sim.inject_fault("stall")
        stale = asyncio.create_task(robot.get_position())  # swallowed by the stall
        await wait_until(lambda: sim.ignored_while_stalled == 1, what="the request swallowed")
        sim.clear_faults()
        robot.new_session()  # what a reset's probe does first
        assert await robot.get_position() == HOME
        with pytest.raises(DeviceTimeout):
            await stale  # its caller still learns of it ...
        assert faults == []  # ... but it is no fault of the new session
        assert robot.health.active_faults == ()
        assert robot.health.connected
    finally:
        await robot.close()


async def test_any_request_that_times_out_marks_the_controller_silent(
    sim: RobotSimulator,
) -> None:
    robot = make_robot(sim.port, timeout=0.3)  # no heartbeat
    faults: list[DeviceFault] = []
    robot.set_fault_listener(faults.append)
    await robot.connect()
    try:
        sim.inject_fault("stall")
        with pytest.raises(DeviceTimeout):
            await robot.is_moving()
        assert [f.code for f in faults] == ["NO_ANSWER"]
        assert robot.health.active_faults == ("robot: no answer within 0.3 s",)
        with pytest.raises(DeviceTimeout):
            await robot.get_position()
        assert len(faults) == 1  # once per onset
        sim.clear_faults()
        assert await robot.get_position() == HOME
        assert robot.health.active_faults == ()
    finally:
        await robot.close()


async def test_a_write_that_fails_leaves_no_unretrieved_future(sim: RobotSimulator) -> None:
    """A call whose write fails raises DeviceDisconnected, and that is all it leaves behind.

    The teardown the failure starts also fails the call's own pending future; nobody
    awaits it, and asyncio would log "Future exception was never retrieved" for it
    when it is collected unless it is retrieved.
    """
    loop = asyncio.get_running_loop()
    unhandled: list[str] = []
    previous = loop.get_exception_handler()
    loop.set_exception_handler(lambda _loop, context: unhandled.append(context["message"]))
    robot = make_robot(sim.port)
    await robot.connect()
    try:
        assert robot._writer is not None
        robot._writer.transport.abort()  # the link breaks under the next write
        try:
            await robot.get_position()
        except DeviceDisconnected:
            pass
        else:
            pytest.fail("a call on a broken link answered")
        await asyncio.sleep(0.05)
        gc.collect()
        await asyncio.sleep(0)
        assert not [m for m in unhandled if "never retrieved" in m], unhandled
    finally:
        loop.set_exception_handler(previous)
        await robot.close()
