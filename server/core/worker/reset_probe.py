"""The reset's live probe of the devices, off the worker's loop.

Why: a reset must ask every device for a live answer (a monitoring reading
can be stale), and that takes up to reset_probe_timeout. The worker does not
wait for it: it starts the probe, goes on deciding events (an e-stop above
all), and the reset comes back to the queue when the probe has answered, to
be decided again on what it found (`server.core.machine.decide`: a stop or a
fault decided meanwhile overtakes it). One reset probes at a time.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from dataclasses import dataclass, field

from server.core.machine.decide import Probed, Stops
from server.core.worker.devices import CellDevices
from server.core.worker.event_queue import Envelope

log = logging.getLogger(__name__)


@dataclass(slots=True)
class ResetProbe:
    """A reset waiting for the devices' live answers, and what was decided since it began."""

    envelope: Envelope
    began: Stops  # e-stops and faults counted when the probe began
    found: list[str] = field(default_factory=list)  # the faults the probe found
    task: asyncio.Task[None] | None = None

    def facts(self) -> Probed:
        """What the reset's second pass decides on (`server.core.machine.decide`)."""
        return Probed(self.began, tuple(self.found))


class ResetProbes:
    """Starts the one reset probe, and hands its reset back to the queue when it answers."""

    def __init__(
        self, devices: CellDevices, timeout: float, requeue: Callable[[Envelope], None]
    ) -> None:
        self.devices = devices
        self.timeout = timeout  # reset_probe_timeout
        self._requeue = requeue
        self.current: ResetProbe | None = None

    @property
    def under_way(self) -> bool:
        """A reset's probe is running (another reset is refused until it answers)."""
        return self.current is not None

    def start(self, envelope: Envelope, began: Stops) -> None:
        probe = ResetProbe(envelope, began)
        probe.task = asyncio.create_task(self._probe(probe), name="reset-probe")
        self.current = probe

    def returned(self, envelope: Envelope) -> ResetProbe | None:
        """The finished probe when `envelope` is its reset coming back, else None."""
        probe = self.current
        if probe is None or probe.envelope is not envelope:
            return None
        self.current = None
        return probe

    async def stop(self) -> list[Envelope]:
        """At shutdown: the probe goes; its reset, still waiting for an answer, is returned."""
        probe, self.current = self.current, None
        if probe is None:
            return []
        if probe.task is not None:
            probe.task.cancel()
            await asyncio.gather(probe.task, return_exceptions=True)
        return [probe.envelope]

    async def _probe(self, probe: ResetProbe) -> None:
        """Probe the devices (bounded by reset_probe_timeout), then queue the reset again."""
        try:
            probe.found = await self.devices.probe_faults(self.timeout)
        except Exception as exc:  # the sender must get an answer whatever went wrong
            log.exception("the reset probe failed")
            probe.found = [f"the reset probe failed: {exc}"]
        self._requeue(probe.envelope)
