"""The cell as one object: devices, bus, worker, and the simulators when asked for.

This is the composition root of the core. The HTTP app and the in-process
façade both wrap a `Cell`, so they share one code path to the machine.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable
from typing import Any

from server.config import Settings
from server.core.bus import Bus
from server.core.devices import CellDevices
from server.core.operations import Operation, default_operations
from server.core.transitions import COMMANDS, Event, normalize_command
from server.core.worker import Outcome, Worker
from server.storage import CellStores

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

    @property
    def devices(self) -> CellDevices:
        assert self.worker is not None, "the cell is not started"
        return self.worker.devices

    async def start(self) -> None:
        devices = self._devices
        if devices is None:
            factory = self._device_factory
            if factory is None:
                from server.drivers.factory import build_devices

                factory = build_devices
            devices, self._release = await factory(self.settings)
        self.stores = CellStores.open(self.settings.data_path)
        if self.settings.camera_simulated and self.settings.commission_simulated_cell:
            from server.drivers.sim.commissioning import commission_simulated_cell

            await commission_simulated_cell(devices, self.stores, self.settings)
        self.worker = Worker(self.settings, devices, self.operations, self.bus, self.stores)
        await self.worker.start()

    async def stop(self) -> None:
        if self.worker is not None:
            await self.worker.stop()
            await self.worker.devices.safe_halt(self.settings.emergency_stop_timeout)
            await self.worker.devices.close()
        if self._release is not None:
            await self._release()
            self._release = None

    async def command(
        self, name: str, *, source: str, data: dict[str, Any] | None = None
    ) -> Outcome:
        """Run an operator command by name (start, pause, estop, ...)."""
        assert self.worker is not None, "the cell is not started"
        canonical = normalize_command(name)
        if canonical is None:
            raise KeyError(name)
        event = COMMANDS[canonical]
        if event is Event.EMERGENCY_STOP:
            return await self.worker.emergency_stop(source=source, data=data)
        return await self.worker.request(event, source=source, data=data)
