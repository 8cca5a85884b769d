"""The bus's direct road: messages handed to a consumer while its task waits.

The WebSocket hub uses it to write each message to a client's socket without
waking that client's task (server/api/ws.py). What a client must never see,
whichever road a message takes: one out of order, one twice, one missing; and
a client that falls behind is still dropped, never waited on.
"""

from __future__ import annotations

import asyncio
import random

import pytest

from server.core.infra.bus import (
    DELIVERY_BUDGET,
    SLOW_CONSUMER,
    Bus,
    BusMessage,
    SubscriptionClosed,
)


class Consumer:
    """A direct consumer that takes messages while `accepting`, noting the road taken."""

    def __init__(self, log: list[tuple[str, int]]) -> None:
        self.log = log
        self.accepting = True
        self.offered = 0

    def __call__(self, message: BusMessage) -> bool:
        self.offered += 1
        if self.accepting:
            self.log.append(("direct", message.seq))
        return self.accepting


async def turns(count: int) -> None:
    for _ in range(count):
        await asyncio.sleep(0)


async def test_a_waiting_subscriber_is_served_directly_without_waking_its_task() -> None:
    bus = Bus()
    log: list[tuple[str, int]] = []
    subscription = bus.subscribe(10)
    subscription.take_directly(Consumer(log))
    task = asyncio.ensure_future(subscription.get())
    await turns(1)  # the task now waits
    for index in range(3):
        bus.publish("progress", {"waypoint": index})
    await turns(3)
    assert log == [("direct", 1), ("direct", 2), ("direct", 3)]
    assert not task.done() and subscription.pending == 0  # its task was never woken
    task.cancel()


async def test_what_the_consumer_refuses_goes_to_the_task_in_order() -> None:
    bus = Bus()
    log: list[tuple[str, int]] = []
    consumer = Consumer(log)
    subscription = bus.subscribe(10)
    subscription.take_directly(consumer)
    task = asyncio.ensure_future(subscription.get())
    await turns(1)
    bus.publish("progress", {})
    await turns(1)
    consumer.accepting = False  # e.g. the socket's transport paused by flow control
    bus.publish("progress", {})
    bus.publish("progress", {})
    await turns(2)
    assert task.done() and task.result().seq == 2
    consumer.accepting = True
    bus.publish("progress", {})  # the task holds 3 still: the direct road stays shut
    await turns(2)
    assert consumer.offered == 2 and log == [("direct", 1)]
    assert [(await subscription.get()).seq for _ in range(2)] == [3, 4]


async def test_a_subscriber_that_falls_behind_on_either_road_is_dropped() -> None:
    bus = Bus()
    log: list[tuple[str, int]] = []
    consumer = Consumer(log)
    consumer.accepting = False
    subscription = bus.subscribe(3)
    subscription.take_directly(consumer)
    task = asyncio.ensure_future(subscription.get())
    await turns(1)
    bus.publish("progress", {})
    await turns(2)  # refused, so the task took it: its send now waits on the client
    assert (await task).seq == 1 and consumer.offered == 1
    for _ in range(4):
        bus.publish("progress", {})
    assert subscription.closed_reason == SLOW_CONSUMER
    with pytest.raises(SubscriptionClosed):
        await subscription.get()
    assert bus.subscriber_count == 0 and log == []


async def test_a_failing_consumer_leaves_its_subscriber_to_the_task() -> None:
    bus = Bus()
    subscription = bus.subscribe(10)

    def broken(message: BusMessage) -> bool:
        raise RuntimeError("a bug in the consumer")

    subscription.take_directly(broken)
    task = asyncio.ensure_future(subscription.get())
    await turns(1)
    bus.publish("progress", {})
    assert (await task).seq == 1


async def test_the_types_filter_applies_to_the_direct_road() -> None:
    bus = Bus()
    log: list[tuple[str, int]] = []
    subscription = bus.subscribe(10, types=["state_changed"])
    subscription.take_directly(Consumer(log))
    task = asyncio.ensure_future(subscription.get())
    await turns(1)
    bus.publish("progress", {})
    bus.publish("state_changed", {})
    bus.publish_sample("device", {})
    await turns(2)
    assert log == [("direct", 2)]
    task.cancel()


async def test_direct_hand_overs_are_spread_over_turns_of_the_loop() -> None:
    bus = Bus()
    log: list[tuple[str, int]] = []
    count = DELIVERY_BUDGET * 2 + 7
    tasks = []
    for _ in range(count):
        subscription = bus.subscribe(10)
        subscription.take_directly(Consumer(log))
        tasks.append(asyncio.ensure_future(subscription.get()))
    await turns(1)
    bus.publish("state_changed", {})
    per_turn = []
    while len(log) < count:
        before = len(log)
        await turns(1)
        if len(log) > before:
            per_turn.append(len(log) - before)
    assert per_turn == [DELIVERY_BUDGET, DELIVERY_BUDGET, 7]
    for task in tasks:
        task.cancel()


@pytest.mark.parametrize("seed", range(20))
async def test_both_roads_together_deliver_every_message_once_in_order(seed: int) -> None:
    """Random bursts, a consumer that accepts at random, a task whose sends take turns."""
    rng = random.Random(seed)
    bus = Bus()
    log: list[tuple[str, int]] = []
    consumer = Consumer(log)
    subscription = bus.subscribe(10_000)
    subscription.take_directly(consumer)
    in_flight: list[int] = []

    async def send_loop() -> None:  # as server/api/ws.py's, with sends that take turns
        while True:
            message = await subscription.get()
            in_flight.append(message.seq)
            await turns(rng.randrange(3))
            log.append(("task", message.seq))
            in_flight.remove(message.seq)

    task = asyncio.create_task(send_loop())
    published = []
    for _ in range(600):
        consumer.accepting = rng.random() < 0.7
        burst = rng.randrange(1, 5) if rng.random() < 0.3 else 0  # quiet turns between
        for _ in range(burst):
            published.append(bus.publish("progress", {}).seq)
        # Nothing is handed over directly while the task has a message in hand.
        before = len(log)
        await turns(1)
        if in_flight:
            assert all(road == "task" for road, _ in log[before:])
    consumer.accepting = True
    while len(log) < len(published):
        await turns(1)
    task.cancel()
    assert [seq for _, seq in log] == published
    assert {road for road, _ in log} == {"direct", "task"}
