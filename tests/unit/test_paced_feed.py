"""The plant's view of a run's progress: thinned to one per interval, nothing else held.

What a plant would notice: a burst of waypoints arrives as its first and its latest;
a transition is never held back and never overtakes the progress before it, so a run's
end comes after its final progress; with nothing else happening the latest progress
still arrives once its interval has passed.
"""

from __future__ import annotations

from server.core.infra.bus import Bus
from server.core.infra.paced_feed import PacedFeed


class StillClock:
    """Time that moves only when the test says: the interval never passes by itself."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def waypoint(bus: Bus, index: int) -> None:
    bus.publish("progress", {"run_id": "r", "waypoint": index, "total": 9})


async def drain(feed: PacedFeed, count: int) -> list[tuple[str, object]]:
    got = []
    for _ in range(count):
        message = await feed.get()
        got.append((message.type, message.data.get("waypoint", message.data.get("to"))))
    return got


async def test_a_burst_of_waypoints_gives_the_first_and_the_latest_before_the_transition() -> None:
    bus = Bus()
    feed = PacedFeed(bus.subscribe(64), interval=0.25, clock=StillClock())
    for index in range(1, 6):
        waypoint(bus, index)
    bus.publish("state_changed", {"to": "IDLE"})
    assert await drain(feed, 3) == [("progress", 1), ("progress", 5), ("state_changed", "IDLE")]
    assert feed.thinned == 3  # waypoints 2, 3 and 4 were replaced by a newer one


async def test_a_waypoint_after_the_interval_goes_at_once() -> None:
    bus = Bus()
    clock = StillClock()
    feed = PacedFeed(bus.subscribe(64), interval=0.25, clock=clock)
    waypoint(bus, 1)
    assert await drain(feed, 1) == [("progress", 1)]
    clock.now = 0.25
    waypoint(bus, 2)
    assert await drain(feed, 1) == [("progress", 2)]
    assert feed.thinned == 0


async def test_the_held_progress_goes_when_its_interval_has_passed() -> None:
    bus = Bus()
    feed = PacedFeed(bus.subscribe(64), interval=0.01)  # the real clock: nothing else comes
    waypoint(bus, 1)
    waypoint(bus, 2)
    assert await drain(feed, 2) == [("progress", 1), ("progress", 2)]
    assert feed.thinned == 0


async def test_other_records_are_never_held_and_keep_their_order() -> None:
    bus = Bus()
    feed = PacedFeed(bus.subscribe(64), interval=10, clock=StillClock())
    waypoint(bus, 1)
    waypoint(bus, 2)
    bus.publish("progress", {"run_id": "r", "recovery_attempt": 1, "cause": "COMM_LOST"})
    bus.publish("error", {"code": "COMM_LOST"})
    waypoint(bus, 3)
    bus.publish("state_changed", {"to": "ERROR"})
    got = await drain(feed, 5)
    assert got == [
        ("progress", 1),
        ("progress", 2),  # held, then handed on ahead of the recovery's record
        ("progress", None),  # the recovery attempt: not thinned
        ("error", None),
        ("progress", 3),  # held, then handed on ahead of the transition
    ]
    assert await drain(feed, 1) == [("state_changed", "ERROR")]


async def test_interval_zero_hands_on_every_waypoint() -> None:
    bus = Bus()
    feed = PacedFeed(bus.subscribe(64), interval=0, clock=StillClock())
    for index in range(1, 5):
        waypoint(bus, index)
    assert [w for _, w in await drain(feed, 4)] == [1, 2, 3, 4]
