"""The cell as a Sparkplug B edge node on Debian's mosquitto, read by a host that decodes
with Eclipse Tahu's schema (tests/sparkplug_host.py), never the cell's own codec.

What a SCADA host would notice: it discovers the node and its device (NBIRTH with
bdSeq and seq 0, DBIRTH with every metric and its type), sees DDATA on a transition
with only what changed and seq counting on, gets both births again when it asks for a
rebirth, and sees NDEATH with the NBIRTH's bdSeq when the server stops and when it is
killed (the broker's will). DCMD commands are ignored unless a token is named, then
run with that token's role, audited, their answer in DDATA.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import os
import signal
import subprocess
import time
from collections.abc import AsyncIterator
from pathlib import Path

from tests.mosquitto import WAIT_S, mosquitto
from tests.processes import server_process
from tests.rig import open_rig
from tests.serving import free_port
from tests.sparkplug_host import Message, sparkplug_host

CELL = "cell-9"
GROUP = "plant-a"
NODE = f"spBv1.0/{GROUP}"

EVERY_METRIC = {
    "State": "String",
    "State/Since": "DateTime",
    "PackML/State": "Int32",
    "Stop Reason/Code": "String",
    "Stop Reason/Message": "String",
    "Run/Id": "String",
    "Run/Workpiece Id": "String",
    "Counts/Good": "Int64",
    "Counts/Defective": "Int64",
    "Counts/Total": "Int64",
    "OEE/OEE": "Double",
    "OEE/Availability": "Double",
    "OEE/Performance": "Double",
    "OEE/Quality": "Double",
    "Devices/Robot/Connected": "Boolean",
    "Devices/Glue/Connected": "Boolean",
    "Devices/Camera/Connected": "Boolean",
}


def _seqs_count_on(messages: list[Message]) -> bool:
    """Within a session, each message's seq is the one before it plus one (mod 256)."""
    seqs = [m.seq for m in messages if m.kind != "NDEATH"]
    return all(b == (a + 1) % 256 for a, b in itertools.pairwise(seqs))


async def test_a_host_discovers_the_cell_reads_it_and_sees_it_leave(tmp_path: Path) -> None:
    with mosquitto(tmp_path / "broker") as broker:
        async with sparkplug_host(broker.port, GROUP) as host:
            async with open_rig(
                tmp_path / "data",
                **broker.cell_login,
                cell_id=CELL,
                sparkplug_group=GROUP,
                mqtt_kpis_interval=1,
            ) as rig:
                # Discovery: NBIRTH (bdSeq, rebirth control, seq 0), then DBIRTH.
                await host.wait(lambda: host.of("DBIRTH"))
                nbirth, dbirth = host.of("NBIRTH")[0], host.of("DBIRTH")[0]
                assert nbirth.topic == f"{NODE}/NBIRTH/{CELL}" and nbirth.seq == 0
                assert nbirth.metrics["bdSeq"][0] == "Int64"
                assert nbirth.metrics["Node Control/Rebirth"] == ("Boolean", False)
                assert dbirth.topic == f"{NODE}/DBIRTH/{CELL}/cell" and dbirth.seq == 1
                # Every metric, with its type; commands are off, so none is offered.
                assert {n: t for n, (t, _) in dbirth.metrics.items()} == EVERY_METRIC
                await host.wait(lambda: host.device_values()["State"] == "IDLE")
                state = await rig.state()
                values = host.device_values()
                assert values["State/Since"] == round(state["since"] * 1000)
                assert values["PackML/State"] == 4  # Idle
                assert values["Stop Reason/Code"] is None and values["Run/Id"] is None
                for device in ("Robot", "Glue", "Camera"):
                    assert values[f"Devices/{device}/Connected"] is True
                # The births can go out before the first KPI reading (OEE null then); the
                # reading follows within mqtt_kpis_interval, as DDATA.
                await host.wait(lambda: host.device_values()["OEE/Availability"] is not None)
                values = host.device_values()
                kpis = (await rig.api.get("/kpis")).json()
                assert values["Counts/Good"] == kpis["quality"]["parts_good"]
                assert values["OEE/Availability"] == kpis["oee"]["availability"]

                # A transition: DDATA with what changed, seq counting on.
                before = len(host.messages)
                response = await rig.api.post("/estop", json={"reason": "sparkplug drill"})
                assert response.status_code == 202
                await host.wait(lambda: host.device_values()["State"] == "ERROR")
                ddata = [m for m in host.messages[before:] if m.kind == "DDATA"]
                first = ddata[0]
                assert first.topic == f"{NODE}/DDATA/{CELL}/cell"
                assert first.metrics["State"] == ("String", "ERROR")
                assert first.metrics["PackML/State"] == ("Int32", 9)  # Aborted
                assert first.metrics["Stop Reason/Code"] == ("String", "EMERGENCY_STOP")
                assert "Counts/Good" not in first.metrics  # only what changed
                assert _seqs_count_on(host.messages)

                # A rebirth on request: both births again, same bdSeq, seq from 0.
                await host.rebirth(CELL)
                await host.wait(lambda: len(host.of("DBIRTH")) == 2)
                again = host.of("NBIRTH")[1]
                assert again.seq == 0 and again.value("bdSeq") == nbirth.value("bdSeq")
                assert host.of("DBIRTH")[1].value("State") == "ERROR"
                assert _seqs_count_on(host.messages[host.messages.index(again) :])

                # A DCMD while commands are off does nothing.
                await host.command(CELL, "Command/Reset")
                await rig.api.get("/state")
                assert (await rig.state())["state"] == "ERROR"

            # A clean stop says NDEATH itself, with its NBIRTH's bdSeq.
            death = await host.wait(lambda: host.of("NDEATH"))
            assert death[0].topic == f"{NODE}/NDEATH/{CELL}" and death[0].seq is None
            assert death[0].value("bdSeq") == nbirth.value("bdSeq")


async def test_commands_run_as_the_named_token_with_its_role(tmp_path: Path) -> None:
    data = tmp_path / "data"
    with mosquitto(tmp_path / "broker") as broker:
        async with open_rig(data, **broker.cell_login, cell_id=CELL) as rig:
            made = await rig.api.post("/tokens", json={"name": "scada", "role": "operator"})
            token_id = made.json()["id"]
        settings = {"sparkplug_group": GROUP, "sparkplug_command_token_id": token_id}
        async with (
            sparkplug_host(broker.port, GROUP) as host,
            open_rig(data, **broker.cell_login, cell_id=CELL, **settings) as rig,
        ):
            dbirth = (await host.wait(lambda: host.of("DBIRTH")))[0]
            offered = {n for n in dbirth.metrics if n.startswith("Command/")}
            assert {"Command/Start", "Command/Estop", "Command/Reset"} <= offered
            assert "Command/Jog" not in offered  # a jog needs a body a boolean cannot carry

            def last() -> tuple[str, int]:
                values = host.device_values()
                return values.get("Command/Last/Name"), values.get("Command/Last/Status")

            # A start the role allows: the same path as HTTP's.
            await host.command(CELL, "Command/Start")
            await host.wait(lambda: last() == ("Command/Start", 202))
            # A stale DCMD (older than mqtt_command_max_age) is refused, not run.
            await host.wait(lambda: host.device_values()["State"] == "IDLE")
            stale_ms = int((time.time() - 3600) * 1000)
            await host.command(CELL, "Command/Estop", sent_ms=stale_ms)
            await host.wait(lambda: last() == ("Command/Estop", 401))
            assert (await rig.state())["state"] == "IDLE"
            # The e-stop any role may send; then a reset the operator's role may not.
            await host.command(CELL, "Command/Estop")
            await host.wait(lambda: last() == ("Command/Estop", 202))
            assert (await rig.wait_state("ERROR"))["stop_reason"]["code"] == "EMERGENCY_STOP"
            await host.command(CELL, "Command/Reset")
            await host.wait(lambda: last() == ("Command/Reset", 403))
            assert (await rig.state())["state"] == "ERROR"

            audit = (await rig.api.get("/audit", params={"limit": 1000})).json()["audit"]
            rows = [(a["action"], a["outcome"]) for a in audit if "Sparkplug" in a["action"]]
            assert any("Command/Reset" in a and o == "refused (403)" for a, o in rows), rows
            assert any("Command/Estop" in a and o == "refused (401)" for a, o in rows), rows
            assert all(token_id in a["principal"] for a in audit if "Command/Start" in a["action"])

            # Revoking the token stops the commands.
            assert (await rig.api.delete(f"/tokens/{token_id}")).status_code in (200, 204)
            await host.command(CELL, "Command/Estop")
            await host.wait(lambda: last() == ("Command/Estop", 401))


@contextlib.asynccontextmanager
async def _server_process(
    port: int, data: Path, env: dict[str, str]
) -> AsyncIterator[subprocess.Popen[str]]:
    with contextlib.ExitStack() as stack:
        yield await asyncio.to_thread(stack.enter_context, server_process(port, data, env))
        await asyncio.to_thread(stack.close)


async def test_ndeath_on_a_clean_stop_and_as_the_will_of_a_killed_server(tmp_path: Path) -> None:
    env = {
        "GLUE_APP_CELL_ID": CELL,
        "GLUE_APP_MQTT_KEEPALIVE": "1",
        "GLUE_APP_SPARKPLUG_GROUP": GROUP,
    }
    with mosquitto(tmp_path / "broker") as broker:
        env.update(broker.cell_environment)
        data = tmp_path / "data"
        data.mkdir()
        async with sparkplug_host(broker.port, GROUP) as host:
            async with _server_process(free_port(), data, env) as server:
                await host.wait(lambda: host.of("DBIRTH"))
                server.send_signal(signal.SIGTERM)
                await asyncio.to_thread(server.wait, WAIT_S)
            deaths = await host.wait(lambda: host.of("NDEATH"))
            assert deaths[0].value("bdSeq") == host.of("NBIRTH")[0].value("bdSeq")

            async with _server_process(free_port(), data, env) as server:
                births = await host.wait(lambda: host.of("NBIRTH")[1:])
                await host.wait(lambda: host.of("DBIRTH")[1:])
                os.kill(server.pid, signal.SIGKILL)  # no word from it: the broker's will
                await asyncio.to_thread(server.wait, WAIT_S)
                deaths = await host.wait(lambda: host.of("NDEATH")[1:])
            assert deaths[0].value("bdSeq") == births[0].value("bdSeq")
            assert deaths[0].seq is None
            # Each session its own bdSeq, across the restart: the host tells the deaths apart.
            assert births[0].value("bdSeq") != host.of("NBIRTH")[0].value("bdSeq")
