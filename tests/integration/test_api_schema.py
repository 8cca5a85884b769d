"""Schemathesis against the committed openapi.json, with every check it has.

Every operation of `openapi.json` gets a bounded, reproducible set of generated
requests (schemathesis' coverage phase plus MAX_EXAMPLES Hypothesis examples,
positive and negative) against the real app under uvicorn on loopback, on
in-process fake devices, twice: once with the admin bearer token and once
without any credentials. Every check schemathesis registers runs on every
answer (ALL_CHECKS): no 5xx, a 405 with Allow for a method a path lacks,
every answer as documented, and the document exact about inputs: what it
calls invalid is refused, what it calls valid is accepted (or refused for the
state of the cell: 404, 409). The admin run authenticates
through schemathesis' own auth (`AdminToken`), so the cases that test a
missing or wrong token really are sent without it.

A deterministic probe complements the random run: every numeric query parameter
the document leaves unbounded above gets its 64-bit extremes once.

The server runs in a thread with its own event loop: schemathesis' pytest
integration is synchronous and its requests block, so the server cannot share
the test's loop. One server serves the whole module; the generated commands
(start, estop, reset, ...) move the cell through its states as they come,
which is the point: whatever the state, no input may produce a 500.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
import secrets
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import hypothesis
import pytest
import requests
import schemathesis
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, rule, run_state_machine_as_test
from pydantic import ValidationError
from schemathesis.checks import CHECKS, load_all_checks
from schemathesis.generation import GenerationMode

from server.api.runtime_settings import RUNTIME_SETTINGS
from server.bootstrap.cell import Cell
from server.common.values import NAME_PATTERN
from server.core.worker.devices import CellDevices
from server.security.policy import required_role
from server.security.tokens import Role
from server.settings.model import Settings
from server.storage.workpieces import WorkpieceIn
from tests.conftest import demo_stores
from tests.fakes import FakeCamera, FakeGlue, FakeRobot
from tests.schema_bounds import unbounded_numbers
from tests.serving import serve

ROOT = Path(__file__).resolve().parents[2]
# Hypothesis examples per operation and mode (the deterministic coverage phase adds its own).
MAX_EXAMPLES = 25

# An explicit configuration (no schemathesis.toml discovery): derandomized, no example database,
# so a CI run makes the same requests as a local one.
CONFIG = schemathesis.Config.from_dict(
    {
        "request-timeout": 10,
        "generation": {
            "max-examples": MAX_EXAMPLES,
            "deterministic": True,
            "database": "none",
        },
    }
)
schema = schemathesis.openapi.from_path(ROOT / "openapi.json", config=CONFIG)

load_all_checks()
# Every check schemathesis has (the registry, not a list written here: a check a new version
# adds runs too), with their default expectations: no custom tolerances.
ALL_CHECKS = list(CHECKS.get_all())

# Tokens this run authenticates with: `DELETE /tokens/{token_id}` stays in the run (it revokes
# tokens that `POST /tokens` created, or answers for unknown ids), but never gets one of these,
# which schemathesis could take from a `GET /tokens` answer. Filled in by the `live` fixture.
_SPARED_TOKEN_IDS: set[str] = set()


@schema.hook
def filter_case(context: schemathesis.HookContext, case: schemathesis.Case) -> bool:
    """Applies to the coverage phase's cases too (filter_path_parameters would not)."""
    token_id = (case.path_parameters or {}).get("token_id")
    spared = isinstance(token_id, str) and token_id in _SPARED_TOKEN_IDS
    return not spared and not breaks_a_stated_order(case) and not refused_for_its_shape(case)


def breaks_a_stated_order(case: schemathesis.Case) -> bool:
    """A valid-by-schema case that breaks a rule the document states across two parameters.

    JSON Schema cannot say that one query parameter must be below another; openapi.json
    says it for tools as `x-before` in the parameter's schema (`since` has `x-before:
    until`), and the server refuses the pair with a 422 naming it. Schemathesis reads
    no extension, so a positive case that breaks the rule is not generated here: this
    reads the rule from the document, it does not excuse an answer.
    """
    if case.meta is None or not case.meta.generation.mode.is_positive:
        return False
    query = case.query or {}
    for parameter in case.operation.definition.raw.get("parameters", []):
        later = parameter.get("schema", {}).get("x-before")
        if later is None or parameter["name"] not in query or later not in query:
            continue
        try:
            if float(query[parameter["name"]]) >= float(query[later]):
                return True
        except (TypeError, ValueError):
            continue
    return False


SHAPE_REFUSALS = ("fill strokes", "fill lines", "distinct, non-collinear")


def refused_for_its_shape(case: schemathesis.Case) -> bool:
    """A valid-by-schema workpiece the planner would refuse for its outline's shape.

    Whether an outline has an inside, crosses itself, survives its bead's offset, or how
    many strokes a fill spacing gives it, no schema can say; the server refuses such a
    part with a 422 naming the field. Only those refusals are spared, read from the
    server's own model: any other way the model and the document disagree still fails.
    """
    if case.meta is None or not case.meta.generation.mode.is_positive:
        return False
    if case.operation.label not in ("PUT /workpieces/{workpiece_id}", "POST /workpieces"):
        return False
    try:
        part = WorkpieceIn.model_validate(case.body)
    except ValidationError as error:
        return all(
            any(words in str(e.get("msg", "")) for words in SHAPE_REFUSALS) for e in error.errors()
        )
    return part.path_problem() is not None


@dataclass
class Live:
    url: str
    admin: dict[str, str]


# The run's admin token, made here and stored in the server's tokens.json before it starts:
# schemathesis generates the coverage phase's cases, with their auth, while collecting.
ADMIN_TOKEN = f"gc_{secrets.token_hex(4)}_{secrets.token_urlsafe(32)}"


def store_admin_token(data: Path) -> None:
    """tokens.json holding ADMIN_TOKEN only (its SHA-256), as the server's token store writes it."""
    entry = {
        "id": ADMIN_TOKEN.split("_")[1],
        "name": "schema test admin",
        "role": "admin",
        "secret_sha256": hashlib.sha256(ADMIN_TOKEN.encode()).hexdigest(),
        "created_at": time.time(),
        "revoked_at": None,
    }
    data.mkdir(parents=True, exist_ok=True)
    (data / "tokens.json").write_text(json.dumps({"tokens": [entry]}), encoding="utf-8")


class AdminToken:
    """Schemathesis' own auth: it leaves the token out of the cases that test its absence."""

    def get(self, case: schemathesis.Case, ctx: schemathesis.AuthContext) -> str:
        return ADMIN_TOKEN

    def set(self, case: schemathesis.Case, data: str, ctx: schemathesis.AuthContext) -> None:
        case.headers = {**(case.headers or {}), "Authorization": f"Bearer {data}"}


class ServerThread(threading.Thread):
    """The app on fakes under uvicorn, in this thread's own event loop, until `stop()`."""

    def __init__(self, settings: Settings) -> None:
        super().__init__(name="schema-test-server", daemon=True)
        self.settings = settings
        self.url = ""
        self.error: BaseException | None = None
        self.ready = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopping: asyncio.Event | None = None

    def run(self) -> None:
        try:
            asyncio.run(self._serve())
        except BaseException as exc:  # uvicorn ends a failed startup with SystemExit
            self.error = RuntimeError(f"the server under test failed: {exc!r}")
            self.error.__cause__ = exc
        finally:
            self.ready.set()

    async def _serve(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stopping = asyncio.Event()
        devices = CellDevices(FakeRobot(speed_factor=50), FakeGlue(), FakeCamera())
        async with serve(Cell(self.settings, devices=devices)) as url:
            self.url = url
            self.ready.set()
            await self._stopping.wait()

    def stop(self, timeout: float = 30) -> None:
        if self._loop is not None and self._stopping is not None and self.is_alive():
            self._loop.call_soon_threadsafe(self._stopping.set)
        self.join(timeout)


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Live]:
    """One server for the module, started with the "demo" workpiece, stopped cleanly after."""
    data = tmp_path_factory.mktemp("schema") / "data"
    settings = Settings(
        data_path=data,
        emergency_stop_timeout=0.5,
        processing_timeout=10,
        robot_communication_timeout=1,
        glue_system_timeout=1,
        vision_processing_timeout=2,
        # The credential-less run sends thousands of requests without a valid token on
        # purpose: not the guessing the throttle is for (a 429 is documented, not expected).
        auth_failure_limit=10_000,
    )
    demo_stores(data)
    store_admin_token(data)
    root_level = logging.getLogger().level  # PATCH /settings may change logging_level
    server = ServerThread(settings)
    server.start()
    try:
        assert server.ready.wait(30), "the server did not start within 30 s"
        if server.error is not None:
            raise server.error
        admin = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
        _SPARED_TOKEN_IDS.add(ADMIN_TOKEN.split("_")[1])
        with httpx.Client(base_url=server.url, headers=admin, timeout=10) as client:
            deadline = time.monotonic() + 10
            while client.get("/state").json()["state"] != "IDLE":
                assert time.monotonic() < deadline, "the cell did not reach IDLE within 10 s"
                time.sleep(0.01)
        yield Live(server.url, admin)
    finally:
        server.stop()
        _SPARED_TOKEN_IDS.clear()
        logging.getLogger().setLevel(root_level)
    assert not server.is_alive(), "the server did not stop within 30 s"
    if server.error is not None:
        raise server.error


@pytest.fixture(scope="module")
def session() -> Iterator[requests.Session]:
    with requests.Session() as http:
        yield http


# --- without credentials -------------------------------------------------------------------
#
# openapi.json documents the access policy (server/security/policy.py, described by
# `server.api.openapi_doc.document_access`): every operation that needs a role declares the bearer
# scheme and its 401 (JSON `{"detail": "..."}` with `WWW-Authenticate: Bearer`) and 403, so the
# schema checks validate a refusal like any other answer; no status is tolerated beyond the
# document. What the document cannot say is that a refused client gets nothing else: a route that
# needs a role must never succeed without credentials (`served_only_to_principals`). The
# generated cases of such an operation may carry an `Authorization` header, since the document
# now declares one; its value is random, so no token, and the run stays anonymous.


# The operations of openapi.json that anyone may call (the policy's `None` entries), written out
# here rather than read from the policy, so that a route opened there by mistake fails here.
OPEN_OPERATIONS = {"GET /health"}


def _needs_role(case: schemathesis.Case) -> bool:
    return case.operation.label not in OPEN_OPERATIONS


def _operations() -> list[tuple[str, str, dict]]:
    return [
        (method.upper(), path, definition)
        for path, methods in schema.raw_schema["paths"].items()
        for method, definition in methods.items()
    ]


def test_the_open_operations_are_the_policys() -> None:
    in_policy = {
        f"{method} {path}"
        for method, path, _ in _operations()
        if required_role(method, path) is None
    }
    assert in_policy == OPEN_OPERATIONS


def _error_view(response: dict) -> str:
    return response["content"]["application/json"]["schema"]["$ref"]


def test_the_document_declares_who_may_call_what() -> None:
    """From the policy table: bearer scheme, role, 401 and 403 where a role is needed; else none."""
    components = schema.raw_schema["components"]
    bearer = components["securitySchemes"]["bearer"]
    assert (bearer["type"], bearer["scheme"]) == ("http", "bearer")
    assert "ErrorView" in components["schemas"]
    for method, path, operation in _operations():
        label, needed = f"{method} {path}", required_role(method, path)
        responses = operation["responses"]
        # trusted_networks applies to every route, open or not
        assert _error_view(responses["403"]) == "#/components/schemas/ErrorView", label
        if needed is None:
            assert "security" not in operation and "x-required-role" not in operation, label
            assert "401" not in responses, label
            assert "trusted_networks" in responses["403"]["description"], label
            continue
        assert operation["security"] == [{"bearer": []}], label
        assert operation["x-required-role"] == needed.label, label
        assert f"`{needed.label}` role" in operation["description"] or needed == Role.VIEWER, label
        unauthenticated = responses["401"]
        assert _error_view(unauthenticated) == "#/components/schemas/ErrorView", label
        assert unauthenticated["headers"]["WWW-Authenticate"]["required"] is True, label
        assert unauthenticated["headers"]["WWW-Authenticate"]["schema"]["enum"] == ["Bearer"]
        if needed > Role.VIEWER:  # a role can be too low
            assert f"`{needed.label}`" in responses["403"]["description"], label


def test_every_number_a_request_carries_is_bounded_in_the_document() -> None:
    """Coordinates, settings, paging: a number with no maximum is where 1e400 got in."""
    document = schema.raw_schema
    found = []
    for method, path, operation in _operations():
        for parameter in operation.get("parameters", []):
            where = f"{method} {path} {parameter['in']} {parameter['name']}"
            found += [where + w for w in unbounded_numbers(parameter["schema"], document)]
        for body in operation.get("requestBody", {}).get("content", {}).values():
            found += [
                f"{method} {path} body {w}" for w in unbounded_numbers(body["schema"], document)
            ]
    assert found == []


def test_the_document_states_the_rules_json_schema_cannot_type() -> None:
    """Names, the settings a PATCH may change, since before until: each stated for clients."""
    components = schema.raw_schema["components"]["schemas"]
    for model, field in (("TokenRequest", "name"), ("WorkpieceIn", "name")):
        assert components[model]["properties"][field]["pattern"] == NAME_PATTERN, model
    change = components["SettingsChange"]
    assert change["additionalProperties"] is False
    assert set(change["properties"]) == set(RUNTIME_SETTINGS)
    for method, path, operation in _operations():
        names = {p["name"]: p for p in operation.get("parameters", []) if p["in"] == "query"}
        if "since" in names:
            assert names["since"]["schema"]["x-before"] == "until", f"{method} {path}"
            assert "before `until`" in names["since"]["description"], f"{method} {path}"


def served_only_to_principals(
    ctx: schemathesis.CheckContext, response: schemathesis.Response, case: schemathesis.Case
) -> bool | None:
    """A route that needs a role never succeeds without credentials."""
    if _needs_role(case):
        assert not 200 <= response.status_code < 300, (
            f"{case.operation.label} needs a role but answered {response.status_code} "
            "without credentials"
        )
    return None


ANONYMOUS_CHECKS = [*ALL_CHECKS, served_only_to_principals]


@schema.parametrize()
@schema.auth.apply(AdminToken)
def test_with_the_admin_token(
    case: schemathesis.Case, live: Live, session: requests.Session
) -> None:
    case.call_and_validate(base_url=live.url, session=session, checks=ALL_CHECKS)


@schema.parametrize()
def test_without_credentials(
    case: schemathesis.Case, live: Live, session: requests.Session
) -> None:
    case.call_and_validate(base_url=live.url, session=session, checks=ANONYMOUS_CHECKS)


# --- numbers past 64 bits ------------------------------------------------------------------
#
# A bounded random run rarely draws 2**63 for an integer that has a minimum and no maximum, yet
# that is where SQLite stops (OverflowError in the driver, a 500). Every numeric parameter the
# document leaves unbounded above is sent its extremes once, deterministically, with the token.
# The values are valid per the document, so the answer must be documented and not a 5xx.

EXTREMES = {"integer": (2**63 - 1, 2**63, 2**64), "number": (1e308,)}


def _numeric_types(parameter_schema: dict) -> set[str]:
    options = parameter_schema.get("anyOf", [parameter_schema])
    return {
        option["type"]
        for option in options
        if option.get("type") in EXTREMES  # bounded or not: past the bound must be a 422
    }


def _a_valid_value(parameter_schema: dict) -> object:
    """A value for a path parameter the probe does not vary (the enum's first, else "demo")."""
    return parameter_schema.get("enum", ["demo"])[0]


def _extremes() -> list[tuple[str, str, str, object]]:
    probes = []
    for path, methods in schema.raw_schema["paths"].items():
        for method, definition in methods.items():
            for parameter in definition.get("parameters", []):
                if parameter["in"] != "query":
                    continue
                for kind in sorted(_numeric_types(parameter["schema"])):
                    probes += [(method, path, parameter["name"], v) for v in EXTREMES[kind]]
    return probes


@pytest.mark.parametrize(("method", "path", "name", "value"), _extremes())
def test_numbers_past_64_bits_are_answered_not_a_500(
    live: Live, session: requests.Session, method: str, path: str, name: str, value: object
) -> None:
    operation = schema[path][method]
    path_parameters = {
        p["name"]: _a_valid_value(p["schema"])
        for p in operation.definition.raw.get("parameters", [])
        if p["in"] == "path"
    }
    case = operation.Case(query={name: value}, path_parameters=path_parameters)
    case.call_and_validate(
        base_url=live.url, session=session, headers=live.admin, checks=ALL_CHECKS
    )


# --- stateful: settings changed, then every read ------------------------------------------
#
# A setting's value is state the random run above rarely combines with a read: the shift
# hours that made every GET /kpis a 500 had to be PATCHed first. This run changes settings
# (generated bodies, valid and invalid) and after each change sends every GET operation of
# the document a generated request, each checked with every check. Hypothesis' own state
# machine drives it (the document has no links for schemathesis' stateful phase to follow).

STATEFUL_RUNS = 4  # sequences of changes
STATEFUL_STEPS = 3  # changes per sequence, each followed by every GET
PATCH_SETTINGS = schema["/settings"]["PATCH"]
GET_OPERATIONS = [
    schema[path]["GET"] for path, methods in schema.raw_schema["paths"].items() if "get" in methods
]


def _strategy(operation, mode: GenerationMode) -> st.SearchStrategy[schemathesis.Case]:
    return operation.as_strategy(generation_mode=mode, hooks=schema.hooks)


SETTINGS_CHANGES = _strategy(PATCH_SETTINGS, GenerationMode.POSITIVE) | _strategy(
    PATCH_SETTINGS, GenerationMode.NEGATIVE
)
READS = [_strategy(operation, GenerationMode.POSITIVE) for operation in GET_OPERATIONS]


def test_every_read_after_any_settings_change_is_answered_as_documented(
    live: Live, session: requests.Session
) -> None:
    def send(case: schemathesis.Case) -> None:
        case.call_and_validate(
            base_url=live.url, session=session, headers=live.admin, checks=ALL_CHECKS
        )

    class SettingsThenReads(RuleBasedStateMachine):
        @rule(change=SETTINGS_CHANGES, data=st.data())
        def change_then_read_everything(self, change: schemathesis.Case, data: st.DataObject):
            send(change)
            for operation, reads in zip(GET_OPERATIONS, READS, strict=True):
                send(data.draw(reads, label=operation.label))

    run_state_machine_as_test(
        SettingsThenReads,
        settings=hypothesis.settings(
            max_examples=STATEFUL_RUNS,
            stateful_step_count=STATEFUL_STEPS,
            deadline=None,
            derandomize=True,
            database=None,
            suppress_health_check=list(hypothesis.HealthCheck),
        ),
    )
