"""The MQTT link's outbox to the broker: in order, each message acknowledged (QoS 1), up to
PUBLISH_WINDOW of them awaiting their acknowledgement at once.

Why a window: one at a time, each message waited a broker round trip for the one
before it, so a stop's event went out two round trips late (behind the run's
message and the retained state). The messages still leave in order on the one
connection; any not acknowledged when the connection ends go back to the front
of the outbox, in order, and are sent again on the next one (at least once, as
QoS 1 promises).
"""

from __future__ import annotations

import asyncio
from collections import deque

import aiomqtt

from server.mqtt.outbox import Entry, Outbox

PUBLISH_WINDOW = 16  # QoS 1 messages awaiting their acknowledgement at once


async def publish_outbox(client: aiomqtt.Client, outbox: Outbox, drained: asyncio.Event) -> None:
    """Publish `outbox` to `client` until the connection ends (raises then); `drained` is set
    whenever everything queued has been acknowledged."""
    sent: deque[tuple[Entry, asyncio.Future[None]]] = deque()
    failed: asyncio.Future[None] = asyncio.get_running_loop().create_future()

    def acknowledged(publishing: asyncio.Future[None]) -> None:
        if publishing.cancelled():
            return
        if (error := publishing.exception()) is not None:
            if not failed.done():
                failed.set_exception(error)
            return
        while sent and _succeeded(sent[0][1]):
            sent.popleft()
        if not sent and not len(outbox):
            drained.set()

    try:
        while True:
            if not len(outbox):
                waiting = asyncio.ensure_future(outbox.wait())
                await asyncio.wait((waiting, failed), return_when=asyncio.FIRST_COMPLETED)
                waiting.cancel()
            while len(sent) >= PUBLISH_WINDOW and not failed.done():
                await asyncio.wait((sent[0][1], failed), return_when=asyncio.FIRST_COMPLETED)
            if failed.done():
                failed.result()  # the publish failed: the connection ends with it
            entry = outbox.take()
            if entry is None:
                continue
            publishing = asyncio.ensure_future(
                client.publish(entry.topic, entry.payload, qos=1, retain=entry.retain)
            )
            sent.append((entry, publishing))
            publishing.add_done_callback(acknowledged)
    finally:
        for entry, pending in reversed(sent):  # not acknowledged: sent again later
            if not _succeeded(pending):
                pending.cancel()
                outbox.put_back(entry)
        if not failed.done():
            failed.cancel()
        elif not failed.cancelled():
            failed.exception()  # retrieved: raised above, or superseded by the cancel


def _succeeded(publishing: asyncio.Future[None]) -> bool:
    return publishing.done() and not publishing.cancelled() and publishing.exception() is None
