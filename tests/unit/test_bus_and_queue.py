"""The bus never waits on a subscriber; the queue orders by lane, then arrival."""

from __future__ import annotations

import asyncio

import pytest

from server.common.errors import EventQueueFull
from server.core.infra.bus import SLOW_CONSUMER, WAKE_BATCH, Bus, SubscriptionClosed
from server.core.machine.transitions import Event
from server.core.worker.event_queue import Envelope, EventQueue, Priority


async def test_sequence_numbers_rise_by_one_for_every_subscriber() -> None:
    bus = Bus()
    first, second = bus.subscribe(10), bus.subscribe(10)
    for index in range(5):
        bus.publish("progress", {"waypoint": index})
    for subscription in (first, second):
        assert [(await subscription.get()).seq for _ in range(5)] == [1, 2, 3, 4, 5]


async def test_a_slow_subscriber_is_closed_and_the_others_keep_receiving() -> None:
    bus = Bus()
    slow, fast = bus.subscribe(3), bus.subscribe(100)
    for index in range(10):
        bus.publish("progress", {"waypoint": index})
        await fast.get()
    with pytest.raises(SubscriptionClosed) as closed:
        await slow.get()
    assert closed.value.reason == SLOW_CONSUMER
    assert bus.subscriber_count == 1
    bus.publish("state_changed", {})
    assert (await fast.get()).seq == 11


async def test_a_subscription_can_filter_message_types() -> None:
    bus = Bus()
    only_states = bus.subscribe(10, types=["state_changed"])
    bus.publish("progress", {})
    bus.publish("state_changed", {"new_state": "IDLE"})
    message = await only_states.get()
    assert message.type == "state_changed" and message.seq == 2


def test_the_ring_gives_what_came_after_a_seq_while_it_still_holds_it() -> None:
    bus = Bus(history=5)
    assert bus.since(0) == [] and Bus().boot != bus.boot  # a numbering of its own
    for index in range(8):
        bus.publish("progress", {"waypoint": index})
    assert [m.seq for m in bus.since(3) or []] == [4, 5, 6, 7, 8]  # 4 is the oldest kept
    assert [m.seq for m in bus.since(6) or []] == [7, 8]
    assert bus.since(8) == [] and bus.since(80) == []
    assert bus.since(2) is None  # 3 is gone: the gap cannot be filled
    assert bus.since(0) is None


def envelope(event: Event, priority: Priority, n: int) -> Envelope:
    return Envelope(f"e{n}", event, "test", {}, priority)


async def test_many_subscribers_are_woken_a_batch_per_loop_turn_and_all_receive() -> None:
    bus = Bus()
    subscribers = [bus.subscribe() for _ in range(WAKE_BATCH * 3 + 5)]
    waiting = [asyncio.ensure_future(s.get()) for s in subscribers]
    await asyncio.sleep(0)  # every consumer is now waiting
    bus.publish("state_changed", {"n": 1})
    woken_per_turn, before = [], 0
    while not all(w.done() for w in waiting):
        await asyncio.sleep(0)
        done = sum(w.done() for w in waiting)
        if done > before:
            woken_per_turn.append(done - before)
        before = done
    # A batch a turn, the rest later: other work (a stop request) runs in between.
    assert woken_per_turn == [WAKE_BATCH, WAKE_BATCH, WAKE_BATCH, 5]
    assert all(w.result().seq == 1 for w in waiting)


async def test_queue_drains_emergency_then_faults_then_requests_each_in_order() -> None:
    queue = EventQueue(capacity=10)
    queue.put(envelope(Event.START_REQUESTED, Priority.REQUEST, 1))
    queue.put(envelope(Event.ERROR_OCCURRED, Priority.FAULT, 2))
    queue.put(envelope(Event.PAUSE_REQUESTED, Priority.REQUEST, 3))
    queue.put(envelope(Event.EMERGENCY_STOP, Priority.EMERGENCY, 4))
    assert [(await queue.get()).event_id for _ in range(4)] == ["e4", "e2", "e1", "e3"]


def test_only_the_request_lane_is_bounded() -> None:
    queue = EventQueue(capacity=2)
    for n in range(2):
        queue.put(envelope(Event.START_REQUESTED, Priority.REQUEST, n))
    with pytest.raises(EventQueueFull):
        queue.put(envelope(Event.START_REQUESTED, Priority.REQUEST, 3))
    queue.put(envelope(Event.EMERGENCY_STOP, Priority.EMERGENCY, 4))
    queue.put(envelope(Event.OPERATION_COMPLETED, Priority.REQUEST, 5), bounded=False)
    assert len(queue) == 4
