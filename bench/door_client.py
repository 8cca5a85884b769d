"""The plant's clients of the door benchmark (bench/estop_doors.py), in a process of their own.

`python -m bench.door_client <http_url> <mqtt_port> <opcua_url> <cell_id>` with the
operator's API token in GLUE_BENCH_TOKEN connects an HTTP client (kept alive, as an
HMI holds one, plus a pool for the flood), an MQTT v5 client (the demo broker's
`operator`) and an OPC UA client (signed in with the token), prints "ready", then
reads commands on its standard input:

- "stop <door> <flood>": sends `flood` pause commands through `door` (http, mqtt,
  opcua) without waiting for their answers, then the door's stop, and prints
  "sent <time>" (time.time() just before the stop was handed to its client) once
  the stop and every flood command are answered. The pauses are refused (409) in
  IDLE and in ERROR: they cost the door and the worker their whole path and change
  nothing.

Being a separate process matters for the same reason as bench/stop_witness.py: a
flood made in the server's process would be charged to the server's stop.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import sys
import time
import uuid
from typing import Any

import aiomqtt
import httpx
from asyncua import Client, ua
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from clients.client.mqtt_signing import sign_command
from server.line.broker import DEMO_PASSWORDS
from server.opcua.address_space import NAMESPACE_URI

QUIET_S = 3.0  # no MQTT answer for this long: the rest were dropped on the way
HTTP_POOL = 64  # the flood's connections (the server holds 64 per address)


class Doors:
    def __init__(self, http: httpx.AsyncClient, flood_http: httpx.AsyncClient) -> None:
        self.http = http
        self.flood_http = flood_http
        self.mqtt: aiomqtt.Client | None = None
        self.opcua: Client | None = None
        self.base = ""
        self.token = ""
        self.reply_to = ""
        self.answers: asyncio.Queue[bytes] = asyncio.Queue()
        self.ns = 0
        self.cell_id = ""

    async def stop(self, door: str, flood: int) -> float:
        if door == "http":
            pending = [asyncio.ensure_future(self.flood_http.post("/pause")) for _ in range(flood)]
            await asyncio.sleep(0)  # the flood's requests begun before the stop
            sent = time.time()
            answer = await self.http.post("/estop")
            assert answer.status_code == 202, answer.text
            await asyncio.gather(*pending)
            return sent
        if door == "mqtt":
            assert self.mqtt is not None
            # Each publish's first step hands its message to the client, in this order;
            # none waits for the broker's acknowledgement of the one before.
            pending = [asyncio.ensure_future(self._publish("pause", None)) for _ in range(flood)]
            await asyncio.sleep(0)
            sent = time.time()
            await self._publish("estop", {"reason": "bench"})
            await asyncio.gather(*pending)
            await self._drain(flood + 1)
            return sent
        assert self.opcua is not None
        calls = [asyncio.ensure_future(self._call("Pause")) for _ in range(flood)]
        await asyncio.sleep(0)
        sent = time.time()
        stop = await self._call("EmergencyStop")
        assert stop.StatusCode.is_good(), stop
        await asyncio.gather(*calls, return_exceptions=True)
        return sent

    async def _drain(self, count: int) -> None:
        """Read the answers, until `count` or none for QUIET_S (a broker that queued too
        many for the cell drops the rest: max_queued_messages)."""
        for _ in range(count):
            try:
                await asyncio.wait_for(self.answers.get(), QUIET_S)
            except TimeoutError:
                return

    async def _publish(self, name: str, body: dict[str, Any] | None) -> None:
        assert self.mqtt is not None
        topic = f"{self.base}/command/{name}"
        properties = Properties(PacketTypes.PUBLISH)
        properties.ResponseTopic = self.reply_to
        payload = json.dumps(sign_command(self.token, topic, body)).encode()
        await self.mqtt.publish(topic, payload, qos=1, properties=properties)

    async def _call(self, method: str) -> ua.CallMethodResult:
        assert self.opcua is not None
        request = ua.CallMethodRequest()
        request.ObjectId = ua.NodeId.from_string(f"ns={self.ns};s={self.cell_id}")
        request.MethodId = ua.NodeId.from_string(f"ns={self.ns};s={self.cell_id}.{method}")
        request.InputArguments = []
        (result,) = await self.opcua.uaclient.call([request])
        return result


async def serve(http_url: str, mqtt_port: int, opcua_url: str, cell_id: str) -> None:
    logging.disable(logging.WARNING)  # aiomqtt counts its pending publishes aloud
    token = os.environ["GLUE_BENCH_TOKEN"]
    headers = {"Authorization": f"Bearer {token}"}
    limits = httpx.Limits(max_connections=HTTP_POOL)
    opcua = Client(opcua_url, timeout=120, watchdog_intervall=60)  # a busy machine: no false alarm
    opcua.set_user("bench")
    opcua.set_password(token)
    async with (
        httpx.AsyncClient(base_url=http_url, headers=headers, timeout=120) as http,
        httpx.AsyncClient(
            base_url=http_url, headers=headers, timeout=120, limits=limits
        ) as flood_http,
        aiomqtt.Client(
            "127.0.0.1",
            mqtt_port,
            username="operator",
            password=DEMO_PASSWORDS["operator"],
            protocol=aiomqtt.ProtocolVersion.V5,
            max_inflight_messages=65535,
        ) as mqtt,
        opcua,
    ):
        doors = Doors(http, flood_http)
        doors.mqtt, doors.opcua, doors.cell_id = mqtt, opcua, cell_id
        doors.base, doors.token = f"glue/{cell_id}", token
        doors.reply_to = f"{doors.base}/response/{uuid.uuid4().hex}"
        doors.ns = await opcua.get_namespace_index(NAMESPACE_URI)
        await mqtt.subscribe(doors.reply_to, qos=1)
        (await http.get("/state")).raise_for_status()

        async def answers() -> None:
            async for message in mqtt.messages:
                doors.answers.put_nowait(bytes(message.payload))  # type: ignore[arg-type]

        reader = asyncio.create_task(answers())
        print("ready", flush=True)
        loop = asyncio.get_running_loop()
        while True:
            words = (await loop.run_in_executor(None, sys.stdin.readline)).split()
            if not words:
                break
            if words[0] == "stop":
                sent = await doors.stop(words[1], int(words[2]))
                print(f"sent {sent}", flush=True)
        reader.cancel()


if __name__ == "__main__":
    asyncio.run(serve(sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4]))
