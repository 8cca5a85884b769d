"""Shift reports on the simulated cell: a run and an e-stop in a window of the real journal
make a report (with the maintenance then due) stored in the journal, served as JSON and as
a printable page, and sent to a webhook and on MQTT (`report`, retained)."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

from server.views.kpis import Window
from tests.integration.test_gluectl import gluectl_process
from tests.integration.test_webhooks import RECEIVER_ON_THIS_HOST, Receiver, hook, receiving, until
from tests.mosquitto import mosquitto, subscriber
from tests.rig import SPRAY_DEMO, open_rig, run

CELL = "cell-r"


async def test_a_shift_report_counts_the_parts_and_the_stops_and_goes_everywhere(
    tmp_path: Path,
) -> None:
    receiver = Receiver()
    with mosquitto(tmp_path / "broker") as broker:
        async with (
            receiving(receiver) as url,
            open_rig(
                tmp_path / "data",
                webhooks=[hook(url, "mes", ["report"])],
                **RECEIVER_ON_THIS_HOST,
                **broker.cell_login,
                cell_id=CELL,
                maintenance_items=[{"name": "wipe nozzle", "every_parts": 1}],
            ) as rig,
        ):
            start = time.time()
            final = await run(rig, "start", SPRAY_DEMO)
            assert final["state"] == "IDLE"
            assert (await rig.api.post("/estop")).status_code in (200, 202)
            await rig.wait_state("ERROR")
            await asyncio.sleep(0.3)  # some time in ERROR, charged to the stop
            assert (await rig.reset()).status_code == 202
            await rig.wait_state("IDLE")
            end = time.time()  # past: the report and /kpis then read the same window
            assert rig.cell.reports is not None
            made = await rig.cell.reports.make(Window(start, end), "shift")

            listed = (await rig.api.get("/reports")).json()["reports"]
            assert [r["id"] for r in listed] == [made["id"]]
            report = (await rig.api.get(f"/reports/{made['id']}")).json()
            kpis = (await rig.api.get("/kpis", params={"since": start, "until": end})).json()
            assert report["period"] == "shift" and report["cell_id"] == CELL
            assert report["window"] == {"start": start, "end": end}
            good, defective = report["parts"]["good"], report["parts"]["defective"]
            assert good + defective == 1  # the one run, inspected
            assert good == kpis["quality"]["parts_good"]
            assert report["oee"] == kpis["oee"]
            assert sum(h["good"] + h["defective"] for h in report["parts"]["by_hour"]) == 1
            stop = report["stop_reasons"][0]
            assert stop["code"] == "EMERGENCY_STOP" and stop["count"] == 1
            assert 0.3 <= stop["seconds"] <= end - start
            # the one part used up the item's interval: the report names it due
            due = report["maintenance"]["items_due"]
            assert [(i["name"], i["status"]) for i in due] == [("wipe nozzle", "due")], due

            page = await rig.api.get(f"/reports/{made['id']}", params={"format": "html"})
            assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
            assert page.text.count("<svg") >= 3 and "EMERGENCY_STOP" in page.text
            assert "wipe nozzle: due" in page.text
            assert (await rig.api.get("/reports/9999")).status_code == 404

            # gluectl report shift: the latest shift's, as a table, as JSON, as the page.
            cli = ("--url", str(rig.api.base_url), "--data-dir", str(tmp_path / "data"))
            table = await gluectl_process(*cli, "report", "shift")
            assert table.code == 0, table.stderr
            assert "EMERGENCY_STOP" in table.stdout and "parts good" in table.stdout
            assert "wipe nozzle due" in table.stdout
            as_json = await gluectl_process(*cli, "--json", "report", "shift")
            assert as_json.json() == report  # type: ignore[comparison-overlap]
            printable = tmp_path / "shift.html"
            wrote = await gluectl_process(*cli, "report", "shift", "--html", str(printable))
            assert wrote.code == 0 and printable.read_text().startswith("<!doctype html>")
            none = await gluectl_process(*cli, "report", "day")
            assert none.code == 3 and "no day report yet" in none.stderr

            notice = (await until(lambda: receiver.notices("report")))[0]
            assert notice["report_id"] == made["id"] and notice["period"] == "shift"
            assert notice["parts"]["good"] == good

            # A subscriber that comes after it still finds the latest report (retained).
            async with subscriber(broker.port, f"glue/{CELL}/report") as late:
                retained = await late.wait(lambda: late.on(f"glue/{CELL}/report"))
                assert retained[0]["report_id"] == made["id"]
                assert retained[0]["stop_reasons"][0]["code"] == "EMERGENCY_STOP"
