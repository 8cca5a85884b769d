"""Soak: hours of operations, operator commands, device faults and resets against
the real server and the simulators, with WebSocket clients coming and going and
bursts of concurrent commands all along, then a verdict from the journal.

Why: the fault tests prove each path once; a long run proves they compose. Races
between an operator's pause and a dispenser alarm, a reset during a reconnection,
a fault while the arm goes home: each rare, all bound to happen over enough
cycles. What must never happen is judged at the end from what the server wrote
and answered, not from what the soak believes it did:

* every journaled transition is a row of the transition table (server/core/machine/transitions.py);
* no HTTP answer is a 5xx other than 503 (the documented "queue full, retry");
* every event the server acknowledged (a 202 or 409 with its event_id) is in the journal;
* every fault ends in ERROR naming the device, with the valve closed and the robot still,
  a reset is refused while the fault lasts and the cell returns to IDLE once it is gone;
* nothing leaks: the open file descriptors at the end are those after the warm-up
  (within soak_figures.FD_SLACK), and once the churning WebSocket clients have all
  left, the server counts none; no churning client met anything but a documented
  answer (soak_traffic.py).

Every other cycle carries a device fault (tests/rig.py DEVICE_FAULTS) at a random
point; every fourth is a burst of concurrent commands from several clients
(tests/reliability/test_storm.py's mix); the others run an operation with random
pauses, resumes, cancels and emergency stops. Resources (memory, open files, the
journal's size) are sampled at two quiet moments, after the warm-up and at the end,
with the answer times of GET /state and of commands in the first and the last
fifth of the run: reported, not judged, save the open files (soak_figures.py).
This process runs the server, the simulators and the clients, so the figures are its.

Run (from the repository root; the exit status is non-zero if anything above failed):
    python -m tests.reliability.soak --duration 30m [--seed N] [--data DIR] [--log-level LEVEL]
or `make soak` (30 minutes; `make soak SOAK=2h` for longer), which also bounds it in time.
Durations: 90s, 30m, 2h, 1h30m, or plain seconds. tests/reliability/test_soak.py runs the
same loop for a few seconds in CI.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import random
import re
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import httpx

from server.common.runtime import limit_malloc_arenas
from server.core.machine.transitions import OPERATIONAL_STATES
from tests.reliability._journal_checks import (
    invalid_transitions,
    journaled_transitions,
    missing_events,
    operation_outcomes,
)
from tests.reliability.soak_figures import FD_SLACK, Latencies, Percentiles, Sample, rss_mb
from tests.reliability.soak_traffic import (
    STORM_CLIENTS,
    ChurnCounts,
    StormCounts,
    WsChurn,
    command_burst,
)
from tests.rig import DEVICE_FAULTS, DROP_REFUSAL_S, TIMEOUT, DeviceFaultKind, Rig, open_rig

OPERATIONAL = {state.value for state in OPERATIONAL_STATES}
SETTLE_S = TIMEOUT * 3 + 5  # bound on a fault being noticed, or an operation ending
RESET_ATTEMPTS = 5
# The start sample is taken after this many cycles, or this share of the run if that
# comes first: first renders and caches are not growth.
WARM_UP_CYCLES = 6
WARM_UP_SHARE = 0.25
STORM_EVERY = 4  # every fourth cycle is a burst of concurrent commands
OVERRUN_S = 300.0  # a cycle still running this long after the run's end: stuck
# Operation → (path, body, weight, first guess of its duration in s).
OPERATIONS: dict[str, tuple[str, dict[str, Any] | None, int, float]] = {
    "spray": ("/start", {"contour_matching": False, "workpiece_id": "demo"}, 4, 1.3),
    "spray-matched": ("/start", {"contour_matching": True}, 2, 1.3),
    "calibrate-robot": ("/calibrate-robot", None, 1, 0.3),
    "calibrate-camera": ("/calibrate-camera", None, 1, 0.8),
    "create-workpiece": ("/create-workpiece", {"workpiece_id": "soak-part"}, 1, 0.3),
}
SPRAYING = {"spray", "spray-matched"}
OPERATOR_ACTIONS = ("run", "run", "pause-resume", "pause-cancel", "cancel", "estop")


class SoakStuck(Exception):
    """The cell could not be brought back to IDLE: the run ends here."""


@dataclass
class SoakReport:
    """What a soak run did and found; `ok` is the verdict."""

    seed: int
    duration_s: float = 0.0
    cycles: int = 0
    operations_started: int = 0
    operation_outcomes: dict[str, int] = field(default_factory=dict)
    faults_injected: Counter[str] = field(default_factory=Counter)
    faults_mid_operation: int = 0
    operator_commands: Counter[str] = field(default_factory=Counter)
    resets_accepted: int = 0
    commands_refused: int = 0
    http_responses: int = 0
    http_503: int = 0
    http_5xx: list[str] = field(default_factory=list)
    transitions_checked: int = 0
    invalid_transitions: list[tuple[str, str, str]] = field(default_factory=list)
    events_acknowledged: int = 0
    lost_events: list[str] = field(default_factory=list)
    safety_findings: list[str] = field(default_factory=list)
    unexpected_errors: list[str] = field(default_factory=list)  # reported, not judged
    rss_start_mb: float = 0.0  # once the rig is up
    rss_warm_mb: float = 0.0  # after the warm-up (or at the end of a shorter run)
    rss_end_mb: float = 0.0
    websocket: ChurnCounts = field(default_factory=ChurnCounts)
    storm: StormCounts = field(default_factory=StormCounts)
    start: Sample | None = None  # after the warm-up, at a quiet moment
    end: Sample | None = None  # once every client has left
    latency_start: dict[str, Percentiles] = field(default_factory=dict)  # first fifth
    latency_end: dict[str, Percentiles] = field(default_factory=dict)  # last fifth
    leaks: list[str] = field(default_factory=list)

    @property
    def rss_growth_mb(self) -> float:
        return self.rss_end_mb - self.rss_warm_mb

    @property
    def operations_completed(self) -> int:
        return self.operation_outcomes.get("completed", 0)

    @property
    def ok(self) -> bool:
        return not (
            self.invalid_transitions
            or self.http_5xx
            or self.lost_events
            or self.safety_findings
            or self.leaks
            or self.websocket.failures
        )

    def as_dict(self) -> dict[str, Any]:
        return {
            **asdict(self),
            "faults_injected": dict(self.faults_injected),
            "operator_commands": dict(self.operator_commands),
            "websocket": self.websocket.as_dict(),
            "storm": self.storm.as_dict(),
            "fd_slack": FD_SLACK,
            "operations_completed": self.operations_completed,
            "rss_growth_mb": round(self.rss_growth_mb, 1),
            "ok": self.ok,
        }

    def table(self) -> str:
        rows = [
            ("seed", self.seed),
            ("duration", f"{self.duration_s:.0f} s"),
            ("cycles run", self.cycles),
            ("operations started", self.operations_started),
            ("operations completed", self.operations_completed),
            ("operation outcomes", _counts(self.operation_outcomes)),
            ("faults injected", sum(self.faults_injected.values())),
            ("  by kind", _counts(self.faults_injected)),
            ("  landed mid-operation", self.faults_mid_operation),
            ("operator commands", _counts(self.operator_commands)),
            ("resets accepted", self.resets_accepted),
            ("commands refused (409)", self.commands_refused),
            ("HTTP responses", self.http_responses),
            ("HTTP 503 (allowed)", self.http_503),
            ("HTTP 5xx other than 503", len(self.http_5xx)),
            ("transitions checked", self.transitions_checked),
            ("invalid transitions", len(self.invalid_transitions)),
            ("events acknowledged", self.events_acknowledged),
            ("lost events", len(self.lost_events)),
            ("safety findings", len(self.safety_findings)),
            ("unexpected operation failures", len(self.unexpected_errors)),
            (
                "RSS start / warm / end",
                f"{self.rss_start_mb:.1f} / {self.rss_warm_mb:.1f} / {self.rss_end_mb:.1f} MB",
            ),
            ("RSS growth after warm-up", f"{self.rss_growth_mb:+.1f} MB"),
            ("WebSocket clients churned", self.websocket.connections),
            ("  messages they read", self.websocket.messages),
            ("  refused as documented", _counts(self.websocket.refused)),
            ("  failures", len(self.websocket.failures)),
            (
                "command bursts",
                f"{self.storm.bursts} of {STORM_CLIENTS} clients, {self.storm.commands} commands",
            ),
            ("  answers", _counts(self.storm.answers)),
            ("leaks", len(self.leaks)),
            ("verdict", "PASS" if self.ok else "FAIL"),
        ]
        width = max(len(name) for name, _ in rows)
        lines = [f"{name:<{width}}  {value}" for name, value in rows]
        details = [
            *(f"invalid transition: {t}" for t in self.invalid_transitions[:20]),
            *(f"HTTP 5xx: {r}" for r in self.http_5xx[:20]),
            *(f"lost event: {e}" for e in self.lost_events[:20]),
            *(f"safety: {s}" for s in self.safety_findings[:20]),
            *(f"leak: {e}" for e in self.leaks[:20]),
            *(f"WebSocket failure: {e}" for e in self.websocket.failures[:20]),
            *(f"unexpected failure: {e}" for e in self.unexpected_errors[:20]),
        ]
        return "\n".join([*lines, "", *self.start_and_end(), *details])

    def start_and_end(self) -> list[str]:
        """Resources at the two quiet moments; answer times in the first and last fifth."""
        start, end = self.start, self.end
        if start is None or end is None:
            return ["no start sample: the run ended before its warm-up did"]
        rows = [
            ("", f"start ({start.at_s:.0f} s)", f"end ({end.at_s:.0f} s)"),
            ("RSS", f"{start.rss_mb:.1f} MB", f"{end.rss_mb:.1f} MB"),
            (
                "open file descriptors",
                start.open_fds,
                f"{end.open_fds} (judged: <= start + {FD_SLACK})",
            ),
            ("journal (db + WAL)", f"{start.journal_mb:.2f} MB", f"{end.journal_mb:.2f} MB"),
            *(
                (
                    f"{kind} p50 / p99",
                    self.latency_start.get(kind, "-"),
                    self.latency_end.get(kind, "-"),
                )
                for kind in ("GET /state", "POST command")
            ),
            ("WebSocket clients counted", start.websocket_clients, end.websocket_clients),
        ]
        width = max(len(str(name)) for name, _, _ in rows)
        first = max(len(str(value)) for _, value, _ in rows)
        return [f"{name:<{width}}  {a!s:<{first}}  {b}" for name, a, b in rows]

    def json_line(self) -> str:
        return json.dumps(self.as_dict(), separators=(",", ":"), default=str)


def _counts(counts: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(counts.items())) or "-"


class Soak:
    """Drives one rig through cycles; every HTTP answer passes through `_on_response`."""

    def __init__(self, rig: Rig, rng: random.Random, report: SoakReport) -> None:
        self.rig = rig
        self.rng = rng
        self.report = report
        self.acknowledged: set[str] = set()
        self.durations = {name: guess for name, (_, _, _, guess) in OPERATIONS.items()}
        self.latencies = Latencies()
        self.auth = {"Authorization": rig.api.headers["authorization"]}
        hooks = rig.api.event_hooks
        hooks["response"] = [*hooks["response"], self._on_response]
        rig.api.event_hooks = hooks

    # --- HTTP ------------------------------------------------------------------------

    async def _on_response(self, response: httpx.Response) -> None:
        self.report.http_responses += 1
        status = response.status_code
        if status == 503:
            self.report.http_503 += 1
        elif status >= 500:
            self.report.http_5xx.append(f"{response.request.method} {response.url.path} {status}")

    async def command(self, path: str, body: dict[str, Any] | None = None) -> httpx.Response:
        """POST a command; an answered event's id is remembered as acknowledged."""
        sent = time.monotonic()
        response = await self.rig.api.post(path, json=body)
        self.latencies.add("POST command", sent, time.monotonic() - sent)
        if response.status_code in (202, 409):
            self.acknowledged.add(response.json()["event_id"])
        if response.status_code == 409:
            self.report.commands_refused += 1
        return response

    async def state(self) -> dict:
        sent = time.monotonic()
        snapshot = await self.rig.state()
        self.latencies.add("GET /state", sent, time.monotonic() - sent)
        return snapshot

    async def websocket_clients(self) -> int:
        return int((await self.rig.api.get("/health")).json()["websocket_clients"])

    # --- one cycle ---------------------------------------------------------------------

    async def cycle(self, number: int) -> None:
        if number % STORM_EVERY == 0:
            await self._storm()
        else:
            await self._operation_cycle(number)
        await self.recover()
        self.report.cycles += 1

    async def _storm(self) -> None:
        """Several clients' commands at once, wherever they lead the cell."""
        base_url = str(self.rig.api.base_url)
        storm = self.report.storm
        answered = await command_burst(
            base_url, self.auth, self.rng, self._on_response, self.latencies.add, storm
        )
        self.acknowledged |= answered

    async def _operation_cycle(self, number: int) -> None:
        name = self._pick_operation()
        fault = self.rng.choice(list(DEVICE_FAULTS.values())) if number % 2 else None
        path, body, _, _ = OPERATIONS[name]
        started = time.monotonic()
        response = await self.command(path, body)
        if response.status_code == 202:
            self.report.operations_started += 1
            if fault is not None:
                await self._fault_during(name, fault)
            else:
                await self._operate(name, started)

    def _pick_operation(self) -> str:
        calibration = self.rig.cell.stores.calibration  # type: ignore[union-attr]
        made_with = calibration.robot_meta.get("camera_calibration_at")
        if made_with != calibration.camera_meta.get("created_at"):
            return "calibrate-robot"  # a camera calibration made the robot calibration stale
        names = list(OPERATIONS)
        return self.rng.choices(names, weights=[OPERATIONS[n][2] for n in names])[0]

    async def _operate(self, name: str, started: float) -> None:
        """Let the operation run, with a random operator command or two on the way."""
        action = self.rng.choice(OPERATOR_ACTIONS) if name in SPRAYING else "run"
        if name not in SPRAYING and self.rng.random() < 0.2:
            action = self.rng.choice(("cancel", "estop"))
        if action != "run":
            await asyncio.sleep(self.rng.uniform(0, self.durations[name]))
            first, _, then = action.partition("-")
            await self._operator(first)
            if then:
                await asyncio.sleep(self.rng.uniform(0, 0.5))
                await self._operator(then)
        snapshot = await self._settled()
        if action == "run" and snapshot["state"] == "IDLE" and snapshot["operation_result"]:
            self.durations[name] = 0.8 * self.durations[name] + 0.2 * (time.monotonic() - started)
        if snapshot["state"] == "ERROR":
            estop = action.endswith("estop")
            if not estop:
                reason = snapshot["stop_reason"] or {}
                self.report.unexpected_errors.append(f"{name}: {reason.get('message')}")
            await self._check_halt(snapshot, "estop" if estop else f"{name} failure")

    async def _operator(self, command: str) -> None:
        self.report.operator_commands[command] += 1
        await self.command(f"/{command}")

    async def _settled(self) -> dict:
        """The state once the operation has ended (a held run is resumed)."""
        deadline = time.monotonic() + SETTLE_S + max(self.durations.values()) * 3
        while (snapshot := await self.state())["state"] in OPERATIONAL:
            if time.monotonic() > deadline:
                raise SoakStuck(f"operation never ended: {snapshot}")
            if snapshot["state"] == "PAUSED":
                await self._operator("resume")
            await asyncio.sleep(0.02)
        return snapshot

    # --- faults ------------------------------------------------------------------------

    async def _fault_during(self, name: str, fault: DeviceFaultKind) -> None:
        if name in SPRAYING and self.rng.random() < 0.3:  # the fault lands on a held run
            await asyncio.sleep(self.rng.uniform(0, self.durations[name] * 0.6))
            await self._operator("pause")
        await asyncio.sleep(self.rng.uniform(0, self.durations[name]))
        stops = self.rig.robot.stop_received_count
        before = self.rig.cell.worker.view.snapshot()  # in this process: no await before it
        if before["state"] == "ERROR":  # a fault of its own came first: not this one's to judge
            reason = (before["stop_reason"] or {}).get("message")
            self.report.unexpected_errors.append(f"{name}, before {fault.name}: {reason}")
            await self._check_halt(before, f"{name} failure")
            return
        injected_at = time.monotonic()
        fault.inject(self.rig)
        self.report.faults_injected[fault.name] += 1
        snapshot, brought_out = await self._await_error(fault)
        if snapshot is None:
            self.report.safety_findings.append(f"{fault.name}: never reached ERROR")
            fault.clear(self.rig)
            return
        if not brought_out and snapshot["previous_state"] in OPERATIONAL:
            self.report.faults_mid_operation += 1
        await self._check_fault_halt(snapshot, fault, stops)
        await self._check_refused(fault, injected_at)
        fault.clear(self.rig)
        if not fault.stop_reaches_robot:
            await self._await_reconnection(fault)

    async def _await_error(self, fault: DeviceFaultKind) -> tuple[dict | None, bool]:
        """ERROR, using the device if the fault would otherwise stay latent; True if so."""
        deadline = time.monotonic() + SETTLE_S
        brought_out = False
        while (snapshot := await self.state())["state"] != "ERROR":
            if time.monotonic() > deadline:
                return None, brought_out
            latent = not fault.noticed_when_idle
            if latent and snapshot["state"] == "PAUSED":
                await self._operator("resume")  # the held run uses the devices again
            elif latent and snapshot["state"] == "IDLE" and not brought_out:
                path, body, _, _ = OPERATIONS[fault.operation]  # the device's next use
                await self.command(path, body)
                brought_out = True
                deadline = time.monotonic() + SETTLE_S
            await asyncio.sleep(0.02)
        return snapshot, brought_out

    async def _check_fault_halt(self, snapshot: dict, fault: DeviceFaultKind, stops: int) -> None:
        reason = snapshot["stop_reason"] or {}
        if reason.get("component") != fault.component:
            self.report.safety_findings.append(f"{fault.name}: stop reason names {reason}")
        await self._check_halt(snapshot, fault.name, valve=fault.valve_closes_at_once)
        if fault.stop_reaches_robot and self.rig.robot.stop_received_count <= stops:
            self.report.safety_findings.append(f"{fault.name}: the halt sent no stop")

    async def _check_halt(self, snapshot: dict, what: str, *, valve: bool = True) -> None:
        """In ERROR: the robot comes to rest and (where it can be told) the valve is closed."""
        if valve and self.rig.glue.valve_open:
            self.report.safety_findings.append(f"{what}: valve open in ERROR ({snapshot})")
        try:
            async with asyncio.timeout(TIMEOUT * 3):
                while self.rig.robot.is_moving:
                    await asyncio.sleep(0.01)
        except TimeoutError:
            self.report.safety_findings.append(f"{what}: the robot still moves in ERROR")

    async def _check_refused(self, fault: DeviceFaultKind, injected_at: float) -> None:
        response = await self.command("/reset")
        if response.status_code == 202:
            self.report.resets_accepted += 1
            window_over = time.monotonic() - injected_at >= DROP_REFUSAL_S
            if fault.stop_reaches_robot or not window_over:
                self.report.safety_findings.append(f"{fault.name}: reset accepted while active")
        elif response.status_code == 409 and fault.refusal not in response.json()["message"]:
            self.report.safety_findings.append(
                f"{fault.name}: reset refused without naming it: {response.json()['message']}"
            )

    async def _await_reconnection(self, fault: DeviceFaultKind) -> None:
        robot = self.rig.cell.devices.robot
        deadline = time.monotonic() + SETTLE_S
        while not robot.health.connected:
            if time.monotonic() > deadline:
                self.report.safety_findings.append(f"{fault.name}: the link never came back")
                return
            await asyncio.sleep(0.05)

    # --- back to IDLE ----------------------------------------------------------------

    async def recover(self) -> None:
        """Clear every injected fault and reset until the cell is IDLE (SoakStuck if not)."""
        for _ in range(RESET_ATTEMPTS):
            snapshot = await self._settled()
            if snapshot["state"] == "IDLE":
                if self.rig.glue.valve_open:
                    self.report.safety_findings.append("valve open in IDLE")
                return
            if snapshot["state"] == "ERROR":
                for fault in DEVICE_FAULTS.values():
                    fault.clear(self.rig)
                response = await self.command("/reset")
                if response.status_code == 202:
                    self.report.resets_accepted += 1
                    continue
            await asyncio.sleep(0.5)
        raise SoakStuck(f"still {(await self.state())['state']} after {RESET_ATTEMPTS} resets")


async def run_soak(duration_s: float, seed: int, data_path: Path) -> SoakReport:
    """Cycle for `duration_s` against a rig in `data_path`, WebSocket clients churning
    all along; the resources are judged at the end, then the journal."""
    report = SoakReport(seed=seed)
    rng = random.Random(seed)
    started = time.monotonic()
    async with open_rig(data_path) as rig:
        soak = Soak(rig, rng, report)
        journal = rig.cell.journal
        assert journal is not None
        journal_path = journal.path
        report.rss_start_mb = rss_mb()
        churn = WsChurn(str(rig.api.base_url), soak.auth, random.Random(seed), soak._on_response)
        report.websocket = churn.counts
        churn.start()
        try:
            await _cycles(soak, churn, duration_s, started, journal_path)
        finally:
            await churn.stop()
        report.end = await _quiet_sample(soak, churn, started, journal_path)
        report.rss_end_mb = report.end.rss_mb
        report.rss_warm_mb = (report.start or report.end).rss_mb
        report.latency_start = soak.latencies.figures(0)
        report.latency_end = soak.latencies.figures(1)
        report.leaks = find_leaks(report.start, report.end)
    report.duration_s = time.monotonic() - started
    report.events_acknowledged = len(soak.acknowledged)
    report.transitions_checked = len(journaled_transitions(journal_path))
    report.invalid_transitions = invalid_transitions(journal_path)
    report.lost_events = sorted(missing_events(journal_path, soak.acknowledged))
    report.operation_outcomes = operation_outcomes(journal_path)
    return report


async def _cycles(
    soak: Soak, churn: WsChurn, duration_s: float, started: float, journal: Path
) -> None:
    """Cycles until `duration_s`; the start sample once warm. A hung cycle is a finding."""
    report = soak.report
    number = 0
    try:
        async with asyncio.timeout(duration_s + OVERRUN_S) as bound:
            while time.monotonic() - started < duration_s:
                number += 1
                await soak.cycle(number)
                warm = number >= WARM_UP_CYCLES
                warm |= time.monotonic() - started >= duration_s * WARM_UP_SHARE
                if warm and report.start is None:
                    report.start = await _quiet_sample(soak, churn, started, journal)
                    churn.resume()
                    soak.latencies.open_windows(time.monotonic(), started + duration_s)
    except SoakStuck as stuck:
        report.safety_findings.append(f"stuck: {stuck}")
    except TimeoutError:
        if not bound.expired():
            raise
        report.safety_findings.append(f"stuck: cycle {number} still ran {OVERRUN_S:g} s late")


async def _quiet_sample(soak: Soak, churn: WsChurn, started: float, journal: Path) -> Sample:
    """Resources once every churning client has left (the churn stays paused) and the
    server counts no WebSocket client (or the bound on that has passed)."""
    await churn.pause()
    deadline = time.monotonic() + SETTLE_S
    while (clients := await soak.websocket_clients()) and time.monotonic() < deadline:
        await asyncio.sleep(0.05)
    return Sample.take(time.monotonic() - started, journal, clients)


def find_leaks(start: Sample | None, end: Sample) -> list[str]:
    """What the end shows leaked since the start: descriptors beyond FD_SLACK, or
    WebSocket clients the server still counts after every one left."""
    leaks = []
    if end.websocket_clients:
        leaks.append(f"{end.websocket_clients} WebSocket clients still counted after all left")
    if start is not None and end.open_fds > start.open_fds + FD_SLACK:
        leaks.append(
            f"open file descriptors grew from {start.open_fds} to {end.open_fds} "
            f"(more than {FD_SLACK})"
        )
    return leaks


_NUMBER = r"\d+(?:\.\d+)?"
_UNIT_S = {"h": 3600.0, "m": 60.0, "s": 1.0}


def parse_duration(text: str) -> float:
    """Seconds in "90s", "30m", "2h", "1h30m" or plain "45" (seconds)."""
    text = text.strip().lower()
    if re.fullmatch(_NUMBER, text):
        seconds = float(text)
    elif re.fullmatch(f"(?:{_NUMBER}[hms])+", text):
        parts = re.findall(f"({_NUMBER})([hms])", text)
        seconds = sum(float(value) * _UNIT_S[unit] for value, unit in parts)
    else:
        raise argparse.ArgumentTypeError(f"not a duration: {text!r} (try 90s, 30m, 2h)")
    if seconds <= 0:
        raise argparse.ArgumentTypeError(f"the duration must be positive, got {text!r}")
    return seconds


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m tests.reliability.soak", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--duration", type=parse_duration, default=parse_duration("30m"))
    parser.add_argument("--seed", type=int, default=None, help="default: a random one, printed")
    parser.add_argument("--data", type=Path, default=None, help="data directory to keep")
    parser.add_argument("--log-level", default="CRITICAL", help="server log level on stderr")
    args = parser.parse_args(argv)
    limit_malloc_arenas()  # as python -m server does, so memory growth means what it would there
    logging.basicConfig(level=args.log_level.upper(), stream=sys.stderr)
    seed = args.seed if args.seed is not None else random.SystemRandom().randrange(2**32)
    print(f"soak: {args.duration:.0f} s, seed {seed}", flush=True)
    with contextlib.ExitStack() as stack:
        data = args.data or Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="soak-")))
        data.mkdir(parents=True, exist_ok=True)
        report = asyncio.run(run_soak(args.duration, seed, data))
    print(report.table())
    print(report.json_line(), flush=True)
    return 0 if report.ok else 1


if __name__ == "__main__":
    sys.exit(main())
