"""Operator mistakes are refused before the transition: 409/422, state unchanged, on record.

Before this, `POST /start {"contour_matching": false}` without a workpiece, or with
an unknown one, was accepted (202) and then drove the cell into ERROR, which needs a
maintenance reset; `create-workpiece` with the id of an existing part replaced it.
"""

from __future__ import annotations

import asyncio

import httpx
import pytest

from server.bootstrap.cell import Cell
from server.core.worker.devices import CellDevices
from server.settings.model import Settings
from tests.conftest import demo_stores
from tests.fakes import FakeCamera, FakeGlue, FakeRobot
from tests.serving import in_process


@pytest.fixture
async def api(fast_settings: Settings):
    """The app in process on fakes, with the demo part in the library and no calibration."""
    devices = CellDevices(FakeRobot(speed_factor=5), FakeGlue(), FakeCamera())
    demo_stores(fast_settings.data_path)
    cell = Cell(fast_settings, devices=devices)
    async with in_process(cell) as client:
        async with asyncio.timeout(10):
            while (await client.get("/state")).json()["state"] != "IDLE":
                await asyncio.sleep(0.01)
        yield client


async def _still_idle_and_on_record(api: httpx.AsyncClient, event_id: str) -> None:
    state = (await api.get("/state")).json()
    assert state["state"] == "IDLE" and state["stop_reason"] is None
    await asyncio.sleep(0.1)  # the audit row is written as the answer leaves
    events = (await api.get("/events", params={"outcome": "refused"})).json()
    assert event_id in [row["id"] for row in events["events"]]
    audit = (await api.get("/audit")).json()["audit"]
    assert any(event_id in (row["detail"] or "") for row in audit)


async def test_start_without_matching_and_without_a_workpiece_is_a_422_naming_it(api) -> None:
    answer = await api.post("/start", json={"contour_matching": False})
    assert answer.status_code == 422
    body = answer.json()
    assert body["errors"][0]["field"] == "workpiece_id"
    assert "workpiece_id is required" in body["detail"] and body["state"] == "IDLE"
    await _still_idle_and_on_record(api, body["event_id"])


async def test_start_with_an_unknown_workpiece_is_a_409_saying_what_to_do(api) -> None:
    answer = await api.post("/start", json={"contour_matching": False, "workpiece_id": "nope"})
    assert answer.status_code == 409
    body = answer.json()
    assert (
        "'nope' is not in the library" in body["message"] and "GET /workpieces" in body["message"]
    )
    await _still_idle_and_on_record(api, body["event_id"])


async def test_start_with_matching_needs_a_robot_calibration_and_allowed_says_so(api) -> None:
    allowed = (await api.get("/operations/start/allowed")).json()
    assert allowed["allowed"] is False and "run calibrate-robot first" in allowed["reason"]
    answer = await api.post("/start")
    assert answer.status_code == 409 and "run calibrate-robot first" in answer.json()["message"]
    await _still_idle_and_on_record(api, answer.json()["event_id"])


async def test_an_empty_library_refuses_matching_and_allowed_gives_the_same_reason(api) -> None:
    assert (await api.delete("/workpieces/demo")).status_code in (200, 204)
    allowed = (await api.get("/operations/start/allowed")).json()
    answer = await api.post("/start")
    assert answer.status_code == 409
    assert "library is empty" in answer.json()["message"]
    assert "library is empty" in allowed["reason"] and allowed["allowed"] is False


async def test_create_workpiece_never_replaces_an_existing_part(api) -> None:
    before = (await api.get("/workpieces/demo")).json()
    answer = await api.post("/create-workpiece", json={"workpiece_id": "demo", "name": "x"})
    assert answer.status_code == 409
    assert "PUT /workpieces/demo" in answer.json()["message"]
    assert (await api.get("/workpieces/demo")).json() == before
    await _still_idle_and_on_record(api, answer.json()["event_id"])


async def test_a_good_start_is_still_accepted(api) -> None:
    answer = await api.post("/start", json={"contour_matching": False, "workpiece_id": "demo"})
    assert answer.status_code == 202 and answer.json()["state"] == "EXECUTING_TRAJECTORY"


SQUARE = [[300.0, -50.0], [400.0, -50.0], [400.0, 50.0], [300.0, 50.0]]
UNPLANNABLE = [
    # (what was sent, the field the 422 names, words of its reason)
    ({"outline_mm": [[0, 0], [0, 0], [0, 0]]}, "outline_mm", "three distinct"),
    ({"outline_mm": [[0, 0], [10, 10], [20, 20]]}, "outline_mm", "non-collinear"),
    (  # a bow-tie: the points of a square in the wrong order
        {"outline_mm": [SQUARE[0], SQUARE[2], SQUARE[1], SQUARE[3]]},
        "outline_mm",
        "crosses itself",
    ),
    (
        {"outline_mm": SQUARE, "spray": {"outline_offset_mm": -50}},
        "spray.outline_offset_mm",
        "inward offset of 50 mm",
    ),
    (
        {"outline_mm": SQUARE, "spray": {"outline": False, "fill": "none"}},
        "spray",
        "nothing to spray",
    ),
]


@pytest.mark.parametrize(("sent", "field", "reason"), UNPLANNABLE)
async def test_a_part_the_planner_would_refuse_is_a_422_at_edit_never_a_run_in_error(
    api, sent, field, reason
) -> None:
    """Accepted before, each started a run that failed with PATH_INVALID (or PATH_EMPTY)
    and left the cell in ERROR, which needs a maintenance reset."""
    before = (await api.get("/workpieces")).json()
    for answer in (
        await api.post("/workpieces", json={"name": "typo", **sent}),
        await api.put("/workpieces/typo", json={"name": "typo", **sent}),
    ):
        assert answer.status_code == 422, answer.text
        problem = answer.json()["errors"][0]
        assert problem["field"] == field and reason in problem["message"], problem
    assert (await api.get("/workpieces")).json() == before
    assert (await api.get("/state")).json()["state"] == "IDLE"


async def test_an_unreadable_body_names_the_body_and_where_it_breaks(api) -> None:
    answer = await api.post(
        "/workpieces", content=b'{"name":"x",,}', headers={"content-type": "application/json"}
    )
    assert answer.status_code == 422
    problem = answer.json()["errors"][0]
    assert problem["field"] == "body", problem  # was "12", the character position
    assert problem["message"].startswith("not valid JSON at character 12")


async def test_create_workpiece_with_nothing_to_spray_is_a_422_before_the_camera_runs(api) -> None:
    spray = {"outline": False, "fill": "none"}
    answer = await api.post("/create-workpiece", json={"name": "x", "spray": spray})
    assert answer.status_code == 422
    problem = answer.json()["errors"][0]
    assert problem["field"] == "spray" and "nothing to spray" in problem["message"]
    assert (await api.get("/state")).json()["state"] == "IDLE"
