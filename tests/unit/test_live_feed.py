"""The live device feed's message and the bus's samples: pure logic, no devices."""

from __future__ import annotations

import asyncio

from server.api.ws import WebSocketHub
from server.core.infra.bus import Bus
from server.views.live import device_message


def test_a_device_message_carries_the_readings_and_their_age() -> None:
    health = {
        "glue": {
            "connected": True,
            "valve_open": True,
            "flow_ml_min": 29.8,
            "pressure_psi": 40.1,
            "status_at": 100.0,
            "last_rtt_ms": 1.2,  # link figures stay in /health
        },
        "robot": {"connected": True, "position": [400.0, 0.0, 20.0, 180.0, 0.0, 0.0]},
        "camera": {"connected": True},
    }
    message = device_message(health, now=100.25)
    assert message["glue"]["valve_open"] is True and message["glue"]["age_ms"] == 250.0
    assert message["glue"]["flow_ml_min"] == 29.8 and "last_rtt_ms" not in message["glue"]
    assert message["robot"]["position"][2] == 20.0
    assert message["robot"]["age_ms"] is None  # no time of reading: unknown, not fresh
    assert set(message) == {"glue", "robot"}


async def test_a_sample_is_unnumbered_not_replayed_and_only_for_who_asks() -> None:
    bus = Bus()
    everything = bus.subscribe()
    devices = bus.subscribe(types=["device", "state_changed"])
    bus.publish("state_changed", {"new_state": "IDLE"})
    sample = bus.publish_sample("device", {"glue": {}})
    bus.publish("progress", {"waypoint": 1})
    assert bus.last_seq == 2 and not sample.numbered
    assert [m.type for m in bus.since(0) or []] == ["state_changed", "progress"]
    await asyncio.sleep(0)
    assert [(await everything.get()).type for _ in range(2)] == ["state_changed", "progress"]
    assert everything.pending == 0
    assert [(await devices.get()).type for _ in range(2)] == ["state_changed", "device"]
    assert "seq" not in sample.as_dict()


def test_the_hub_never_caches_a_sample_under_a_seq() -> None:
    bus = Bus()
    hub = WebSocketHub(max_clients=2, buffer=8)
    record = bus.publish("progress", {"waypoint": 1})
    first = bus.publish_sample("device", {"n": 1})
    second = bus.publish_sample("device", {"n": 2})
    assert '"n": 1' in hub.encode(first) and '"n": 2' in hub.encode(second)
    assert '"seq": 1' in hub.encode(record)
