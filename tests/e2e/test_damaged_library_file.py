"""One damaged library file never stops the server (nor makes GET/PUT of the part
answer 500): it is listed as damaged with the reason, the
server starts, PUT repairs it and DELETE removes it."""

from __future__ import annotations

import time

import httpx

from tests.processes import server_process
from tests.serving import admin_headers, free_port

OUTLINE = {"name": "demo again", "outline_mm": [[340, -40], [460, -40], [460, 40], [340, 40]]}


def test_a_truncated_part_file_is_listed_as_damaged_then_repaired_and_removed(tmp_path) -> None:
    library = tmp_path / "workpieces"
    library.mkdir(parents=True)
    (library / "demo.json").write_text('{"id": "demo", "name": "De', encoding="utf-8")
    port = free_port()
    with server_process(port, tmp_path, {"GLUE_APP_SIMULATION_SPEED_FACTOR": "10"}):
        client = httpx.Client(
            base_url=f"http://127.0.0.1:{port}", headers=admin_headers(tmp_path), timeout=30
        )
        deadline = time.monotonic() + 60
        while client.get("/state").json()["state"] == "INITIALIZING":
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert client.get("/state").json()["state"] == "IDLE"
        listing = client.get("/workpieces").json()
        assert listing["workpieces"] == []
        [damaged] = listing["damaged"]
        assert damaged["id"] == "demo" and "not valid JSON" in damaged["reason"]
        one = client.get("/workpieces/demo")
        assert one.status_code == 409 and "PUT /workpieces/demo repairs it" in one.json()["detail"]
        repaired = client.put("/workpieces/demo", json=OUTLINE)
        assert repaired.status_code == 200, repaired.text
        assert client.get("/workpieces/demo").json()["name"] == "demo again"
        assert client.get("/workpieces").json()["damaged"] == []
        (library / "demo.json").write_text("[]", encoding="utf-8")  # valid JSON, not a part
        assert client.get("/workpieces").json()["damaged"][0]["id"] == "demo"
        assert client.delete("/workpieces/demo").status_code == 204
        assert client.get("/workpieces").json() == {"workpieces": [], "damaged": []}
