"""Stand-ins for cells on a real broker: the MQTT topic contract's messages, published
with paho, so the line view and `gluectl line` are tested before and apart from the
cell's own publisher.

`publish_cell` publishes one cell's retained status, state and KPIs (and a progress
message) and disconnects cleanly. Run as a module, a cell publishes the same with a
last will of `offline` and stays connected with a short keep-alive until it is
stopped: SIGKILL closes its socket (the broker sends the will at once), SIGSTOP
freezes it with the socket open (the broker sends the will once the keep-alive runs
out), which is what a hung or unplugged cell looks like.

    python -m tests.line_publisher --port PORT --cell cell-3 --keepalive 1
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from server.line.broker import DEMO_PASSWORDS

PREFIX = "glue"


def state_message(cell_id: str, state: str, **extra: Any) -> dict[str, Any]:
    """A `glue/<cell_id>/state` body as the contract has it."""
    return {
        "cell_id": cell_id,
        "state": state,
        "since": time.time(),
        "stop_reason": None,
        "run_id": None,
        "workpiece_id": None,
        **extra,
    }


def kpis_message(oee: float | None) -> dict[str, Any]:
    """The part of a GET /kpis body the line reads (oee.oee), with its siblings."""
    return {"oee": {"availability": 1.0, "performance": 1.0, "quality": 1.0, "oee": oee}}


def connected_client(port: int, cell_id: str, keepalive: int = 60) -> mqtt.Client:
    client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"test-{cell_id}")
    client.username_pw_set("cell", DEMO_PASSWORDS["cell"])  # the demo broker's cell user
    will = {"cell_id": cell_id, "status": "offline", "time": None, "clean": False}
    client.will_set(f"{PREFIX}/{cell_id}/status", json.dumps(will).encode(), qos=1, retain=True)
    connected = threading.Event()
    client.on_connect = lambda *_: connected.set()
    client.connect("127.0.0.1", port, keepalive=keepalive)
    client.loop_start()
    assert connected.wait(30), "the broker did not accept the connection"
    return client


def publish(client: mqtt.Client, cell_id: str, kind: str, body: Any, retain: bool) -> None:
    payload = body if isinstance(body, bytes) else json.dumps(body).encode()
    client.publish(f"{PREFIX}/{cell_id}/{kind}", payload, qos=1, retain=retain).wait_for_publish(30)


def publish_contract(
    client: mqtt.Client,
    cell_id: str,
    state: dict[str, Any],
    oee: float | None,
    progress: dict[str, Any] | None = None,
) -> None:
    online = {"cell_id": cell_id, "status": "online", "time": time.time(), "clean": True}
    publish(client, cell_id, "status", online, retain=True)
    publish(client, cell_id, "state", state, retain=True)
    publish(client, cell_id, "kpis", kpis_message(oee), retain=True)
    if progress is not None:
        publish(client, cell_id, "progress", {"cell_id": cell_id, **progress}, retain=False)


def publish_cell(
    port: int,
    cell_id: str,
    state: dict[str, Any],
    oee: float | None,
    progress: dict[str, Any] | None = None,
) -> None:
    """One cell's retained topics (and a progress message), then a clean disconnect."""
    client = connected_client(port, cell_id)
    try:
        publish_contract(client, cell_id, state, oee, progress)
    finally:
        client.disconnect()
        client.loop_stop()


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--cell", required=True)
    parser.add_argument("--keepalive", type=int, default=1)
    args = parser.parse_args()
    client = connected_client(args.port, args.cell, args.keepalive)
    publish_contract(client, args.cell, state_message(args.cell, "IDLE"), 0.5)
    print("published", flush=True)
    threading.Event().wait()  # until killed


if __name__ == "__main__":
    main()
