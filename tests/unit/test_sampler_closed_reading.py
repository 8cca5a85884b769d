"""The run's sampler waits for the dispenser's first count after the close, and only for one
that can come (server/quality/sampler.py)."""

from __future__ import annotations

import asyncio
import time
from types import SimpleNamespace

import pytest

from server.drivers.base import DeviceHealth
from server.quality.sampler import RunSampler

pytestmark = pytest.mark.asyncio


def poll(glue: SimpleNamespace, *, valve_open: bool, total_ml: float | None) -> None:
    """What the glue driver's monitor writes into its details at a status read."""
    now = time.time()
    details = glue.health.details
    details.update(valve_open=valve_open, flow_ml_min=30.0 if valve_open else 0.0, status_at=now)
    if total_ml is not None:
        details.update(dispensed_ml=total_ml, dispensed_at=now)


def sampler_of(glue: SimpleNamespace) -> RunSampler:
    return RunSampler(SimpleNamespace(health=DeviceHealth("robot")), glue, 0.05)


async def test_it_takes_the_first_closed_count_after_the_close() -> None:
    glue = SimpleNamespace(health=DeviceHealth("glue"))
    sampler = sampler_of(glue)
    poll(glue, valve_open=False, total_ml=5.0)
    sampler._take_flow()
    sampler.opened(1)
    poll(glue, valve_open=True, total_ml=5.2)
    sampler._take_flow()
    sampler.closed()
    # The valve's read-back: the valve and status_at, not the count.
    glue.health.details.update(valve_open=False, status_at=time.time())
    waiting = asyncio.create_task(sampler.closed_reading(5.0))
    await asyncio.sleep(0.05)
    assert not waiting.done()
    poll(glue, valve_open=False, total_ml=5.5)  # the monitor's next poll
    assert await waiting is True
    assert sampler.samples.flows[-1].total_ml == 5.5


async def test_no_wait_for_a_dispenser_that_keeps_no_count() -> None:
    glue = SimpleNamespace(health=DeviceHealth("glue"))
    sampler = sampler_of(glue)
    poll(glue, valve_open=False, total_ml=None)
    sampler._take_flow()
    sampler.opened(1)
    poll(glue, valve_open=True, total_ml=None)
    sampler._take_flow()
    sampler.closed()
    async with asyncio.timeout(1.0):  # far below `within`: it does not wait at all
        assert await sampler.closed_reading(30.0) is False
