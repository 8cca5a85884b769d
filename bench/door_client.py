"""The plant's clients of the door benchmark (bench/estop_doors.py), in a process of their own.

`python -m bench.door_client <http_url> <mqtt_port> <opcua_url> <cell_id>` with the
operator's API token in GLUE_BENCH_TOKEN connects an HTTP client (kept alive, as an
HMI holds one, plus a pool for the flood), an MQTT v5 client (the demo broker's
`operator`) and an OPC UA client (signed in with the token), prints "ready", then
reads commands on its standard input:

- "flood <door> <count>": sends `count` pause commands through `door` without waiting
  for their answers and prints "begun" once the first of them are on their way (the
  flood of another client than the stop's, as a runaway script beside the HMI);
  "finish" waits until all are answered and prints "done";
- "stop <door> <flood>": sends `flood` pause commands through `door` (http, mqtt,
  opcua) without waiting for their answers, then the door's stop, and prints
  "sent <time> <written>" once the stop and every flood command are answered:
  `time`, time.time() just before the stop was handed to its client; `written`,
  when the stop's bytes were handed to the kernel (`StopWrites`), so the time the
  client's own loop and its outgoing queue held the stop is told apart from the
  server's. The pauses are refused (409) in
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
from asyncio import selector_events
from typing import Any

import aiomqtt
import httpx
import paho.mqtt.client as paho_client
from asyncua import Client, ua
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from clients.client.mqtt_signing import sign_command
from server.line.broker import DEMO_PASSWORDS
from server.opcua.address_space import NAMESPACE_URI

QUIET_S = 3.0  # no MQTT answer for this long: the rest were dropped on the way
MAX_OPCUA_REQUESTS = 500  # the server lets a connection have this many waiting
HTTP_POOL = 64  # the flood's connections (the server holds 64 per address)


class StopWrites:
    """When this process last handed a stop's bytes to the kernel, whatever the door.

    Each client's lowest write is wrapped: asyncio's socket transport (httpx over
    anyio, asyncua) and paho's socket send (aiomqtt). A write is a stop's if it
    holds the stop's marker: the HTTP request line, the MQTT topic, the OPC UA
    method's node id. A transport that must buffer a write (the socket full) sends
    it later, so the stamp is then the buffering's; it is not reset between trials.
    """

    MARKERS = (b"POST /estop ", b"/command/estop", b".EmergencyStop")
    last = 0.0

    @classmethod
    def install(cls) -> None:
        transport: Any = selector_events._SelectorSocketTransport
        write = transport.write

        def stamped_write(self: Any, data: Any) -> None:
            cls._look(data)
            write(self, data)

        transport.write = stamped_write
        sock_send = paho_client.Client._sock_send

        def stamped_send(self: Any, buf: bytes | bytearray) -> int:
            cls._look(buf)
            return sock_send(self, buf)

        paho_client.Client._sock_send = stamped_send  # type: ignore[method-assign]

    @classmethod
    def _look(cls, data: Any) -> None:
        chunk = bytes(data[:512])
        if any(marker in chunk for marker in cls.MARKERS):
            cls.last = time.time()


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

        self.flooding: list[asyncio.Future[Any]] = []
        self.flooded_answers = 0  # MQTT answers the flood waits for

    async def flood(self, door: str, count: int) -> None:
        """Send `count` pauses through `door`, without waiting for their answers; return
        once the first are on their way (each future's first step hands its request to the
        client, in this order)."""
        if door == "mqtt":
            self.flooded_answers += count
        self.flooding += [asyncio.ensure_future(self._pause(door)) for _ in range(count)]
        await asyncio.sleep(0)

    async def _pause(self, door: str) -> Any:
        if door == "http":
            return await self.flood_http.post("/pause")
        if door == "mqtt":
            return await self._publish("pause", None)
        return await self._call("Pause")

    async def finish(self) -> None:
        """Wait for every flooded command's answer."""
        pending, self.flooding = self.flooding, []
        await asyncio.gather(*pending, return_exceptions=True)
        answers, self.flooded_answers = self.flooded_answers, 0
        if answers:
            await self._drain(answers)

    async def stop(self, door: str, flood: int) -> float:
        """The door's stop behind `flood` pauses of this same client (for MQTT the same
        connection, so the broker delivers the stop after them; for OPC UA the same
        session; for HTTP a pool of connections beside the HMI's own)."""
        await self.flood(door, flood)
        sent = time.time()
        if door == "http":
            answer = await self.http.post("/estop")
            assert answer.status_code == 202, answer.text
        elif door == "mqtt":
            await self._publish("estop", {"reason": "bench"})
            self.flooded_answers += 1
        else:
            stop = await self._call("EmergencyStop")
            assert stop.StatusCode.is_good(), stop
        await self.finish()
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
    # asyncua's client sends at most 100 requests at a time by default and holds the rest
    # until answers come: the flood's calls and the stop all on their way at once instead.
    opcua.uaclient.set_max_concurrent_requests(MAX_OPCUA_REQUESTS)
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
                print(f"sent {sent} {StopWrites.last}", flush=True)
            elif words[0] == "flood":
                await doors.flood(words[1], int(words[2]))
                print("begun", flush=True)
            elif words[0] == "finish":
                await doors.finish()
                print("done", flush=True)
        reader.cancel()


if __name__ == "__main__":
    StopWrites.install()
    asyncio.run(serve(sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4]))
