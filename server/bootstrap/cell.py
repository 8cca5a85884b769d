"""The cell as one object: devices, bus, worker, and the simulators when asked for.

The composition root (`server/bootstrap/app.py: create_app`) builds it beside the
plant interfaces and the webhooks, which subscribe to its bus. The HTTP app and
the in-process façade both wrap a `Cell`, so they share one code path to the machine.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import Awaitable, Callable
from typing import Any

from pydantic import ValidationError

from server.bootstrap.logging_setup import log_path
from server.core.infra.bus import Bus
from server.core.machine.events import AuditNote, Outcome, Payload, StopPayload
from server.core.machine.faults import classify
from server.core.machine.transitions import (
    COMMANDS,
    OPERATION_OF_STATE,
    OPERATIONAL_STATES,
    Command,
    Event,
    State,
)
from server.core.operations import Operation, default_operations
from server.core.worker.devices import CellDevices
from server.core.worker.snapshot import SnapshotFile
from server.core.worker.stop import EmergencyStops
from server.core.worker.view import CellView
from server.core.worker.worker import Worker
from server.drivers.base import DeviceFault
from server.orders.book import OrderBook
from server.orders.fresh_part import fresh_part_per_run
from server.settings.model import Settings
from server.settings.recording import RecordingSettings
from server.settings.runtime import restore_saved
from server.settings.watch import WatchSettings
from server.storage import CellStores
from server.storage.journal import Journal, records
from server.storage.permissions import tighten_data_directory
from server.views.live import DeviceFeed
from server.views.recording import FlightRecorder
from server.views.reports import ShiftReports
from server.vision.process import IMAGE_PROCESS
from server.watch.watcher import CellWatch

log = logging.getLogger(__name__)

DeviceFactory = Callable[[Settings], Awaitable[tuple[CellDevices, Callable[[], Awaitable[None]]]]]


class Cell:
    """Owns the running machine; start() brings it up, stop() takes it down."""

    def __init__(
        self,
        settings: Settings,
        *,
        devices: CellDevices | None = None,
        device_factory: DeviceFactory | None = None,
        operations: dict[str, Operation] | None = None,
    ) -> None:
        self.settings = settings
        self.bus = Bus()
        self.operations = default_operations()
        if operations:
            self.operations.update(operations)
        self._devices = devices
        self._device_factory = device_factory
        self._release: Callable[[], Awaitable[None]] | None = None
        self.worker: Worker | None = None
        self.stores: CellStores | None = None
        self.journal: Journal | None = None
        self._snapshot_file: SnapshotFile | None = None
        self._feed: DeviceFeed | None = None
        # Each run's device samples, journaled (server/views/recording.py).
        self.recorder: FlightRecorder | None = None
        # The report of each shift and production day as it ends (server/views/reports.py).
        self.reports: ShiftReports | None = None
        # Production orders (server/orders/): drive the cell through `command`, like a person.
        self.orders: OrderBook | None = None
        # The cell watching itself (server/watch/): resources, links, error rate, trends.
        self.watch: CellWatch | None = None
        # The settings changed at runtime and in force (saved in the data directory).
        self.runtime_settings: set[str] = set()

    @property
    def devices(self) -> CellDevices:
        assert self.worker is not None, "the cell is not started"
        return self.worker.devices

    @property
    def view(self) -> CellView:
        """The one read interface to the running cell (see server/core/worker/view.py)."""
        assert self.worker is not None, "the cell is not started"
        return self.worker.view

    @property
    def stops(self) -> EmergencyStops:
        """Where every e-stop is made (server/core/worker/stop.py)."""
        assert self.worker is not None, "the cell is not started"
        return self.worker.stops

    @property
    def started(self) -> bool:
        return self.worker is not None

    async def start(self) -> None:
        """Bring the cell up: devices, data directory, journal, state, worker, subscribers.

        The devices are built (the simulators started, each client made) while the
        journal is opened and checked: neither needs the other, and each is mostly a
        thread's wait (SQLite, the simulators' start), so in turn they added up to a
        third of a start-up's time. The taught marker layout is put in force only once
        the devices are built: the simulated table is printed from the configured one.
        """
        settings = self.settings
        if settings.camera_simulated:
            # The simulated camera draws in the image process: started first, its imports
            # and the first frame overlap the rest of the start. With a real camera it starts
            # on the first image work (a calibration, a run): nothing needs it before.
            IMAGE_PROCESS.warm_up()
        building: asyncio.Task[tuple[CellDevices, Callable[[], Awaitable[None]] | None]]
        building = asyncio.create_task(self._build_devices(), name="device-build")
        try:
            previous, snapshot_file = await self._open_records()
        except BaseException:
            await self._abandon(building)
            raise
        try:
            devices, self._release = await building
        except BaseException:  # no devices, no cell: the records' threads end with the start
            if self.journal is not None:
                await asyncio.to_thread(self.journal.stop)
            if snapshot_file is not None:
                await asyncio.to_thread(snapshot_file.stop)
            raise
        assert self.stores is not None and self.journal is not None
        restore_taught_layout(settings, self.stores.markers.applied)
        self.runtime_settings = restore_runtime_settings(settings, self.stores)
        self._snapshot_file = snapshot_file
        interruption = await asyncio.to_thread(find_interruption, self.journal, previous)
        if interruption:
            log.error(
                "restart after an interruption: %s; the cell stays in ERROR until reset",
                interruption,
            )
        if settings.camera_simulated and settings.commission_simulated_cell:
            from server.bootstrap.commissioning import commission_simulated_cell

            await commission_simulated_cell(devices, self.stores, settings)
        self.worker = Worker(
            settings,
            devices,
            self.operations,
            self.bus,
            self.stores,
            journal=self.journal,
            snapshot_file=snapshot_file,
            interruption=interruption,
        )
        await self.worker.start()
        recording = settings.section(RecordingSettings)
        self.reports = ShiftReports(
            self,
            self.journal,
            settings.cell_id,
            lambda: settings.shift_hours,  # changed at run time by PATCH /settings
            recording.shift_start_hour,
            care=self.worker.care.state,
        )
        if recording.shift_reports:
            self.reports.start()
        self._feed = DeviceFeed(devices, self.bus, self.worker.view, settings.device_push_interval)
        self.recorder = recorder = FlightRecorder(recording, self.journal, self.worker.view)
        self._feed.listeners.append(recorder.sample)
        self.worker.view.on_run_ended(lambda ended: recorder.run_ended(ended.run_id))
        self._feed.start()
        self.watch = CellWatch(
            lambda: settings.section(WatchSettings),
            settings.data_path,
            devices.health,
            self.worker.alerts.warn,
            self.journal,
            cleared=self.worker.alerts.cleared,
        )
        self.worker.view.on_run_ended(self.watch.on_run_ended)
        await self.watch.start()
        # The simulated cell presents a fresh part after each one (a real cell: a person or
        # a conveyor does; the next start finds the part by contour matching, or fails).
        next_part = getattr(devices.camera, "present_next_part", None)
        if next_part is not None:
            fresh_part_per_run(self.worker.view, next_part)
        self.orders = book = OrderBook(self, self.journal, next_part=next_part)
        self.worker.orders = book  # a start while an order is active makes a part of it
        await self.orders.start()

    async def _build_devices(
        self,
    ) -> tuple[CellDevices, Callable[[], Awaitable[None]] | None]:
        """The devices given, or built by the factory (with what releases them)."""
        if self._devices is not None:
            return self._devices, None
        factory = self._device_factory
        if factory is None:
            from server.bootstrap.devices import build_devices

            factory = build_devices
        return await factory(self.settings)

    async def _abandon(
        self, building: asyncio.Task[tuple[CellDevices, Callable[[], Awaitable[None]] | None]]
    ) -> None:
        """The start failed: what was built for the devices is released, not left running."""
        try:
            _, release = await building
        except Exception:
            return
        if release is not None:
            await release()

    async def _open_records(self) -> tuple[dict[str, Any] | None, SnapshotFile | None]:
        """The data directory, the stores, the journal (checked) and the state snapshot: the
        state the last run left, and the snapshot file (started)."""
        settings = self.settings
        for note in settings.compatibility_notes():
            log.warning("setting ignored: %s", note)
        # The data directory for the cell's user only, however the server was started.
        await asyncio.to_thread(tighten_data_directory, settings.data_path, [log_path(settings)])
        self.stores = CellStores.open(settings.data_path)
        self.journal = Journal(
            settings.journal_file,
            synchronous=settings.journal_synchronous,
            retention_days=settings.analytics_retention_days,
        )
        checking = time.perf_counter()
        await asyncio.to_thread(self.journal.open)
        log.info("start-up: journal opened and checked in %.3f s", time.perf_counter() - checking)
        self.journal.start(asyncio.get_running_loop())
        record_journal_damage(self.journal)
        if not settings.state_persistence:
            return None, None
        snapshot_file = SnapshotFile(
            settings.data_file(settings.persistence_file, "state.json"),
            settings.persistence_interval,
        )
        journal, load = self.journal, snapshot_file.load  # reads: off the loop
        previous = await asyncio.to_thread(lambda: last_state(journal, load()))
        snapshot_file.start()
        return previous, snapshot_file

    async def stop(self) -> None:
        """Take the cell down: what runs (`stop_running`), then its records (`close_records`).

        A subscriber that journals what it abandons (the webhooks) is stopped between
        the two by whoever started it (`server/bootstrap/plant.py: stop_cell`)."""
        await self.stop_running()
        await self.close_records()

    async def stop_running(self) -> None:
        """Orders, feed, watch, the worker (devices halted and closed), reports; the
        journal stays open."""
        if self.orders is not None:
            await self.orders.stop()
            self.orders = None
        if self._feed is not None:
            await self._feed.stop()
            self._feed = None
        if self.watch is not None:
            await self.watch.stop()
            self.watch = None
        if self.recorder is not None:  # what the last run left, before the journal stops
            self.recorder.flush()
        if self.worker is not None:
            await self.worker.stop()
            await self.worker.devices.safe_halt(self.settings.emergency_stop_timeout)
            await self.worker.devices.close()
        if self.reports is not None:
            await self.reports.stop()

    async def close_records(self) -> None:
        """The journal, the state snapshot, and what was built for the devices."""
        if self.journal is not None:
            await asyncio.to_thread(self.journal.stop)
        if self._snapshot_file is not None:
            await asyncio.to_thread(self._snapshot_file.stop)
        if self._release is not None:
            await self._release()
            self._release = None

    async def command(
        self,
        command: Command,
        *,
        source: str,
        payload: Payload | None = None,
        audit: AuditNote | None = None,
        asked_at_estops: int | None = None,
    ) -> Outcome:
        """Run an operator command (start, pause, estop, ...) with its typed payload.

        `audit` says who sent it: its row is committed with the event, before the answer.
        An e-stop is the stop service's (`server/core/worker/stop.py`): halted at once,
        queued ahead of everything waiting. Any other command is refused if an e-stop was
        made after it reached its door: `asked_at_estops`, the count then (`stops_now()`;
        by default, now), so a door that holds commands in a line takes it as each arrives.
        """
        assert self.worker is not None, "the cell is not started"
        event = COMMANDS[command]
        if event is Event.EMERGENCY_STOP:
            stop = payload if isinstance(payload, StopPayload) else StopPayload()
            return await self.stops.stop(source=source, payload=stop, audit=audit)
        if asked_at_estops is None:
            asked_at_estops = self.stops_now()
        return await self.worker.request(
            event, source=source, payload=payload, audit=audit, asked_at_estops=asked_at_estops
        )

    def stops_now(self) -> int:
        """The e-stops counted so far: what a door notes as a command reaches it."""
        return self.stops.requested

    def alert(self, code: str, message: str, component: str) -> None:
        """An alert on every channel (log, journal, WebSocket, MQTT, OPC UA, webhooks), for
        what a person did that others must hear of, such as a configuration change."""
        assert self.worker is not None, "the cell is not started"
        self.worker.alerts.warn(code, message, component, severity="alert")

    def report_fault(self, fault: DeviceFault) -> None:
        """Stop the cell on a fault found outside the drivers (an order's defect limit): the
        fault path closes the valve first and enters ERROR with this as its stop reason."""
        assert self.worker is not None, "the cell is not started"
        self.worker.report_fault(fault)


def restore_taught_layout(settings: Settings, taught: list[tuple[float, float]] | None) -> None:
    """Put the marker layout last taught and applied (POST /calibration/markers/apply) in force.

    Why it outranks the configured marker_positions_mm: it was measured on this table
    by the robot itself, after the configuration was written. A taught layout the
    settings now refuse (the workspace was changed since) is left out, loudly.
    """
    if taught is None or [tuple(p) for p in settings.marker_positions_mm] == taught:
        return
    merged = {**settings.model_dump(), "marker_positions_mm": taught}
    try:
        Settings.model_validate(merged)
    except ValidationError as exc:
        problem = "; ".join(error["msg"] for error in exc.errors())
        log.error("the taught marker layout is not put in force: %s", problem)
        return
    settings.marker_positions_mm = list(taught)
    log.info("marker layout in force: the one taught and applied (GET /calibration/markers)")


def restore_runtime_settings(settings: Settings, stores: CellStores) -> set[str]:
    """Put the settings changed at runtime and saved (PATCH /settings) back in force.

    Why they stand over the environment and the config file: see
    server/settings/runtime.py. Each one that does is logged with the value it
    replaces; a saved file that cannot be read is logged and left alone (the
    cell starts on its configuration, and the next change rewrites the file).
    """
    assert stores.runtime_settings is not None
    try:
        saved = stores.runtime_settings.load()
    except ValueError as exc:
        log.error("the settings changed at runtime are not put in force: %s", exc)
        return set()
    before = settings.model_dump()
    applied, problems = restore_saved(settings, saved)
    for problem in problems:
        log.error("saved runtime setting: %s", problem)
    for name in applied:
        log.info(
            "setting %s=%r: changed at runtime and saved (was %r from the configuration)",
            name,
            getattr(settings, name),
            before[name],
        )
    if "logging_level" in applied:  # the handlers were set up from the configured level
        logging.getLogger().setLevel(settings.logging_level)
    return set(applied)


def record_journal_damage(journal: Journal) -> None:
    """What start-up found wrong with the journal, in its own `errors`: /health shows it
    until the server stops, this row for as long as retention keeps it."""
    code = "JOURNAL_DAMAGED"
    for damage in journal.damage:
        record = records.error(
            damage.found_at,
            code,
            damage.message,
            "journal",
            classify(code),
            "",
            State.INITIALIZING.value,
        )
        journal.append([record], durable=False)


def last_state(journal: Journal, previous: dict[str, Any] | None) -> dict[str, Any] | None:
    """The state the last run of the server left: its snapshot's, unless the journal
    recorded a later change.

    Why: a change's snapshot is written once the change's commit is durable and
    its sender answered (`Recorder.answer_when_durable`), so a server killed in
    between leaves a snapshot one change behind what was answered. A reset
    acknowledged that way must not come back as ERROR, nor an e-stop as IDLE.
    The journal's newer transition then stands, with the fault that took the
    cell to ERROR if it did.
    """
    newest = journal.query("transitions", limit=1)
    if not newest:
        return previous
    last = newest[0]
    if previous is not None:
        since = previous.get("since")
        since = since if isinstance(since, int | float) else 0.0  # a file written by hand
        if last["new_state"] == previous.get("state") or last["time"] <= since:
            return previous
    state: dict[str, Any] = {"state": last["new_state"], "since": last["time"]}
    faults = journal.faults_of(last["event_id"]) if last["new_state"] == State.ERROR.value else []
    if faults:
        state["stop_reason"] = {"code": faults[0]["code"], "message": faults[0]["message"]}
    log.warning(
        "the state snapshot was behind the journal (%s, journal %s); the journal's stands",
        (previous or {}).get("state", "none"),
        last["new_state"],
    )
    return state


def find_interruption(journal: Journal, previous: dict[str, Any] | None) -> str | None:
    """Why the last run of the server ended mid-operation, or None if it did not.

    The journal's unfinished operations are the evidence (their rows are closed
    as interrupted here); the snapshot adds the state (EXECUTING or PAUSED).
    """
    unfinished = journal.unfinished_operations()
    state = (previous or {}).get("state")
    if not unfinished:
        if state in {s.value for s in OPERATIONAL_STATES}:
            return f"interrupted during {state}; the server stopped before the operation ended"
        if state == State.ERROR.value:  # ERROR is latched: only a person's reset ends it
            first = (previous or {}).get("stop_reason") or {}
            if first.get("code") == "INTERRUPTED" and first.get("message"):
                # Already an earlier restart's account of the first fault: say it once,
                # not wrapped one level deeper on every restart.
                return str(first["message"])
            reason = first.get("message", "unknown")
            return f"the cell was in ERROR when the server stopped (first fault: {reason})"
        return None
    journal.mark_interrupted([op["run_id"] for op in unfinished], time.time())
    last = unfinished[-1]
    kind_states = [s.value for s, kind in OPERATION_OF_STATE.items() if kind == last["kind"]]
    if state not in kind_states:
        state = kind_states[0]
    message = f"interrupted during {state}"
    progress = json.loads(last["progress"] or "{}")
    if progress.get("waypoint") and progress.get("total"):
        message += f" at waypoint {progress['waypoint']} of {progress['total']}"
    return f"{message} (run {last['run_id']}); the server stopped before the operation ended"
