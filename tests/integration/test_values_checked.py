"""Every value is checked where it enters: a bad one is a 422 naming the field, never a 500.

The app called in process (httpx's ASGI transport), on in-process fake devices: what
is checked is the API's answer, not the socket. Each test sends what a script or a
careless hand could send (Infinity, 1e400, "8" for 8, true for 1, a NUL in a name,
an inverted time window, a parameter the route does not take) and checks the
answer names what is wrong and that nothing was changed.
"""

from __future__ import annotations

import httpx
import pytest

from server.api.runtime_settings import RUNTIME_SETTINGS
from server.bootstrap.cell import Cell
from server.core.worker.devices import CellDevices
from server.settings.model import Settings
from tests.conftest import demo_stores
from tests.fakes import FakeCamera, FakeGlue, FakeRobot
from tests.serving import in_process

OUTLINE = [[340.0, -40.0], [460.0, -40.0], [460.0, 40.0], [340.0, 40.0]]


@pytest.fixture
async def api(fast_settings: Settings):
    demo_stores(fast_settings.data_path)
    cell = Cell(fast_settings, devices=CellDevices(FakeRobot(50), FakeGlue(), FakeCamera()))
    async with in_process(cell) as client:
        yield client


def _fields(response: httpx.Response) -> list[str]:
    assert response.status_code == 422, response.text
    return [problem["field"] for problem in response.json()["errors"]]


async def _patch_raw(api: httpx.AsyncClient, text: str) -> httpx.Response:
    """PATCH /settings with a body as written (JSON5-ish numbers Python's parser accepts)."""
    return await api.patch(
        "/settings", content=text.encode(), headers={"content-type": "application/json"}
    )


@pytest.mark.parametrize("number", ["Infinity", "-Infinity", "NaN", "1e400"])
async def test_a_non_finite_setting_is_refused_and_kpis_keep_answering(api, number) -> None:
    before = (await api.get("/settings")).json()
    refused = await _patch_raw(api, f'{{"design_cycle_time_s": {number}}}')
    assert _fields(refused) == ["design_cycle_time_s"]
    assert (await api.get("/settings")).json() == before
    assert (await api.get("/kpis")).status_code == 200


# Every setting PATCH /settings takes as a number, at a value a bare `> 0` would let in.
SUBNORMAL = "3.55e-276"
# (0 means something for the two left out: no delay, no out-of-tolerance time allowed.)
RUNTIME_NUMBERS = [
    name
    for name in RUNTIME_SETTINGS
    if Settings.model_fields[name].annotation is float
    and name not in ("error_recovery_delay", "dispensing_max_out_of_tolerance_s")
]


@pytest.mark.parametrize("name", RUNTIME_NUMBERS)
async def test_a_subnormal_setting_is_refused_naming_it(api, name) -> None:
    """shift_hours 3.55e-276 made every GET /kpis a 500; processing_timeout 1e-320 made the
    next start fail at once. Each is a 422 naming the field, and nothing changes."""
    before = (await api.get("/settings")).json()
    refused = await _patch_raw(api, f'{{"{name}": {SUBNORMAL}}}')
    assert _fields(refused) == [name]
    assert (await api.get("/settings")).json() == before
    assert (await api.get("/kpis")).status_code == 200


@pytest.mark.parametrize("hours", [0.25, 744])
async def test_kpis_answer_at_either_end_of_the_shift_range(api, hours) -> None:
    assert (await api.patch("/settings", json={"shift_hours": hours})).status_code == 200
    for params in ({}, {"until": 0}, {"since": 1e11}, {"until": 1e11}, {"since": 0}):
        answer = await api.get("/kpis", params=params)
        assert answer.status_code == 200, (params, answer.text)


@pytest.mark.parametrize(
    "body",
    [
        '{"processing_timeout": 1e400}',  # would disable the run's time limit
        '{"error_state_timeout": 1e12}',  # no alert within 30 000 years
        '{"error_recovery_delay": 1e9}',
        '{"design_cycle_time_s": 1e300}',
    ],
)
async def test_a_setting_beyond_its_bound_is_refused(api, body) -> None:
    refused = await _patch_raw(api, body)
    assert _fields(refused) == [body.split('"')[1]]


@pytest.mark.parametrize(
    "body",
    [
        {"shift_hours": "8"},
        {"shift_hours": True},
        {"error_recovery_attempts": True},
        {"error_recovery_attempts": 2.5},
        {"auto_recovery_enabled": "yes"},
        {"auto_recovery_enabled": 1},
    ],
)
async def test_settings_refuse_strings_and_booleans_for_numbers(api, body) -> None:
    [(key, _)] = body.items()
    assert _fields(await api.patch("/settings", json=body)) == [key]


async def test_numbers_are_read_as_json_schema_reads_them(api) -> None:
    """12 is a valid decimal and 4.0 a valid whole number, as openapi.json's types say."""
    changed = await api.patch("/settings", json={"shift_hours": 12, "error_recovery_attempts": 4.0})
    assert changed.status_code == 200, changed.text
    assert changed.json()["changed"] == {
        "shift_hours": {"old": 8.0, "new": 12.0},
        "error_recovery_attempts": {"old": 3, "new": 4},
    }


@pytest.mark.parametrize(
    "spray", [{"speed_mm_s": "100"}, {"speed_mm_s": True}, {"outline": "yes"}, {"outline": 1}]
)
async def test_a_workpiece_refuses_strings_and_booleans_for_numbers(api, spray) -> None:
    body = {"name": "plate", "outline_mm": OUTLINE, "spray": spray}
    [field] = _fields(await api.post("/workpieces", json=body))
    assert field == f"spray.{next(iter(spray))}"
    assert (await api.get("/workpieces")).json()["workpieces"][0]["id"] == "demo"  # only it


async def test_an_outline_point_as_text_or_beyond_the_table_is_refused(api) -> None:
    as_text = {"name": "plate", "outline_mm": [["340", -40.0], *OUTLINE[1:]]}
    assert _fields(await api.post("/workpieces", json=as_text)) == ["outline_mm.0.0"]
    far = {"name": "plate", "outline_mm": [[340.0, -40.0], [1e6, 0.0], *OUTLINE[2:]]}
    assert _fields(await api.post("/workpieces", json=far)) == ["outline_mm.1.0"]


@pytest.mark.parametrize(
    "name", ["bad\x00name", "two\nlines", "tab\there", "\x1b[31mred", "abc\u202edcba", "x\u2066y"]
)
async def test_names_refuse_control_and_bidi_override_characters(api, name) -> None:
    token = await api.post("/tokens", json={"name": name, "role": "viewer"})
    assert _fields(token) == ["name"]
    part = await api.post("/workpieces", json={"name": name, "outline_mm": OUTLINE})
    assert _fields(part) == ["name"]
    capture = await api.post("/create-workpiece", json={"name": name})
    assert _fields(capture) == ["name"]
    assert [t["name"] for t in (await api.get("/tokens")).json()["tokens"]] == ["initial admin"]


async def test_a_name_in_any_script_is_accepted(api) -> None:
    created = await api.post("/tokens", json={"name": "Müller – Linie 2 · 東京", "role": "viewer"})
    assert created.status_code == 201


@pytest.mark.parametrize(
    "path", ["/history", "/operations", "/errors", "/events", "/kpis", "/audit", "/audit.csv"]
)
async def test_since_after_until_is_a_422_naming_since(api, path) -> None:
    for since, until in ((200.0, 100.0), (100.0, 100.0)):
        response = await api.get(path, params={"since": since, "until": until})
        assert _fields(response) == ["query.since"], path
        assert "before until" in response.json()["detail"]


async def test_the_refusal_shows_both_times_as_sent(api) -> None:
    """Formatted with :g, any real Unix time read 1.79576e+09 on both sides."""
    response = await api.get("/history", params={"since": 1795759700, "until": 1795759600})
    assert "since=1795759700.0 is not before until=1795759600.0" in response.json()["detail"]


async def test_since_after_until_on_an_export_is_a_422_naming_since(api) -> None:
    response = await api.get("/export/events.csv", params={"since": 5, "until": 1})
    assert _fields(response) == ["query.since"]


@pytest.mark.parametrize(
    ("path", "parameter"),
    [
        ("/state", "verbose"),
        ("/history", "sinse"),
        ("/kpis", "window"),
        ("/audit", "who"),
        ("/export/errors.csv", "kind"),  # a filter of the operations table, not of errors
    ],
)
async def test_a_query_parameter_the_route_does_not_take_is_refused(api, path, parameter) -> None:
    response = await api.get(path, params={parameter: "1"})
    assert _fields(response) == [f"query.{parameter}"]


async def test_an_estop_is_never_refused_over_its_query(api) -> None:
    """The one route whose answer matters more than its input: it stops the cell anyway."""
    stopped = await api.post("/estop", params={"reason": "typed in the wrong place"})
    assert stopped.status_code == 202 and stopped.json()["state"] == "ERROR"


async def test_kpis_since_a_time_still_to_come_is_an_empty_shift(api) -> None:
    """Valid by the document (since alone, within its bounds), so answered: nothing yet."""
    response = await api.get("/kpis", params={"since": 9e10})
    assert response.status_code == 200, response.text
    report = response.json()
    assert report["window"]["start"] == 9e10 and report["window"]["hours"] == 8.0
    assert report["operations_ended"] == 0 and report["available_time_s"] == 0.0


@pytest.mark.parametrize(
    ("path", "parameter", "wrong", "right"),
    [
        ("/operations", "outcome", "faild", "failed"),
        ("/operations", "kind", "trajectroy", "trajectory"),
        ("/events", "outcome", "rejected", "refused"),
        ("/errors", "classification", "fatal", "critical"),
        ("/export/operations.csv", "outcome", "interupted", "interrupted"),
    ],
)
async def test_a_filter_of_a_closed_set_refuses_a_value_outside_it(
    api, path, parameter, wrong, right
) -> None:
    """A typo matched no row and answered an empty page, as if nothing had failed."""
    assert _fields(await api.get(path, params={parameter: wrong})) == [f"query.{parameter}"]
    assert (await api.get(path, params={parameter: right})).status_code == 200
