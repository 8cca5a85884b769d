"""The MQTT outbox: bounded, in order, the oldest stream message dropped and counted,
the latest of each retained topic never dropped (pure: no broker)."""

from __future__ import annotations

from server.mqtt.outbox import Entry, Outbox
from server.mqtt.topics import Topics


def drain(outbox: Outbox) -> list[Entry]:
    taken = []
    while (entry := outbox.take()) is not None:
        taken.append(entry)
    return taken


def test_the_oldest_stream_messages_are_dropped_and_counted() -> None:
    outbox = Outbox(limit=3)
    for i in range(5):
        outbox.put(Entry("c/event", str(i).encode()))
    assert outbox.dropped == 2
    assert [e.payload for e in drain(outbox)] == [b"2", b"3", b"4"]


def test_a_retained_topic_keeps_its_latest_in_place_and_is_never_dropped() -> None:
    outbox = Outbox(limit=2)
    outbox.put(Entry("c/state", b"IDLE", retain=True))
    outbox.put(Entry("c/event", b"e1"))
    outbox.put(Entry("c/state", b"ERROR", retain=True))
    for i in range(2, 6):
        outbox.put(Entry("c/event", f"e{i}".encode()))
    assert outbox.dropped == 3  # e1, e2, e3: stream only; the superseded state is not counted
    assert [(e.topic, e.payload) for e in drain(outbox)] == [
        ("c/state", b"ERROR"),
        ("c/event", b"e4"),
        ("c/event", b"e5"),
    ]


def test_a_failed_publish_goes_back_to_the_front_unless_replaced() -> None:
    outbox = Outbox(limit=10)
    outbox.put(Entry("c/event", b"e1"))
    outbox.put(Entry("c/state", b"A", retain=True))
    first = outbox.take()
    assert first is not None
    outbox.put_back(first)
    state = drain(outbox)[1]
    outbox.put(Entry("c/state", b"B", retain=True))
    outbox.put_back(state)  # a newer state is waiting: the old one is not sent again
    assert [e.payload for e in drain(outbox)] == [b"B"]


def test_command_topics_name_one_command() -> None:
    topics = Topics("glue", "cell-1")
    assert topics.command_name("glue/cell-1/command/start") == "start"
    assert topics.command_name("glue/cell-1/command/a/b") is None
    assert topics.command_name("glue/cell-2/command/start") is None
    assert topics.commands == "glue/cell-1/command/+"


def test_progress_of_runs_that_ended_is_discarded_the_rest_kept_in_order() -> None:
    outbox = Outbox(limit=4)
    outbox.put(Entry("c/progress", b"old-1", run_id="old"))
    outbox.put(Entry("c/run", b"old ended"))
    outbox.put(Entry("c/state", b"IDLE", retain=True))
    outbox.put(Entry("c/progress", b"new-1", run_id="new"))
    outbox.put(Entry("c/progress", b"old-2", run_id="old"))  # late, after the run ended
    assert outbox.discard_progress(keep_run="new") == 2
    assert outbox.dropped == 0  # discarded as stale, not counted as lost
    # Nothing stale holds a place under the bound: two more stream messages fit.
    outbox.put(Entry("c/event", b"e1"))
    outbox.put(Entry("c/event", b"e2"))
    assert outbox.dropped == 0
    assert [e.payload for e in drain(outbox)] == [b"old ended", b"IDLE", b"new-1", b"e1", b"e2"]
