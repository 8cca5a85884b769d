"""A storm of concurrent, mixed operator commands from many clients at once.

The unit tests show the queue refusing when full and the engine refusing what
the table forbids, one case at a time. Under load these meet: many HTTP
handlers, the bounded request lane, the e-stop that skips it, operations
finishing and failing in between, and the journal writer behind all of them.
What must hold whatever the interleaving:

* every command gets an answer the API documents (202, 409 or 503), each with
  its reason, and 503 with Retry-After: never a 500, never another 4xx;
* the health check answers all along;
* the journal tells one continuous story made only of transitions the table
  allows, and holds every event the API answered for;
* afterwards the cell still works: e-stop, reset, IDLE, and a full spray run.

The queue is made small so that 503 really happens; the test fails if any of
202, 409 and 503 was never seen, because then it did not exercise that path.
"""

from __future__ import annotations

import asyncio
import itertools
import random
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

from tests.reliability._journal_checks import (
    invalid_transitions,
    journaled_transitions,
    missing_events,
)
from tests.rig import SPRAY_DEMO, Rig, open_rig

CLIENTS = 40  # bounded for CI: concurrent HTTP clients
COMMANDS_PER_CLIENT = 75  # bounded for CI: 3000 commands in all
# event_queue_size: below the commands the HTTP door serves at once (ADMITTED, 4), so the
# request lane can fill
QUEUE_SIZE = 2
SEED = 20261203
HEALTH_POLL_S = 0.05
BACKOFF_S = 0.05

# Every operator command (server/api/commands.py), weighted towards the ones
# that move the machine through its spraying states.
MIX: dict[str, tuple[int, dict[str, Any] | None]] = {
    "start": (6, SPRAY_DEMO),
    "pause": (4, None),
    "resume": (4, None),
    "cancel": (3, None),
    "estop": (1, {"reason": "storm"}),
    "reset": (4, None),
    "calibrate-robot": (1, None),
    "calibrate-camera": (1, None),
    "create-workpiece": (1, None),
}
ANSWERS = {202, 409, 503}
# Parts of an answer's message that mean the server failed, whatever the status.
TROUBLE = ("internal error", "journal write failed")


@dataclass(frozen=True)
class Answer:
    command: str
    status: int
    body: dict[str, Any]
    retry_after: str | None


@dataclass(frozen=True)
class HealthCheck:
    status: int
    commands_answered: int  # how far the storm was when this answer came


def body_of(response: httpx.Response) -> dict[str, Any]:
    try:
        body = response.json()
    except ValueError:
        return {"text": response.text}
    return body if isinstance(body, dict) else {"json": body}


async def storm_client(url: str, headers: dict[str, str], seed: int, answers: list[Answer]) -> None:
    """One client sending COMMANDS_PER_CLIENT random commands, one after another."""
    rng = random.Random(seed)
    names = list(MIX)
    weights = [weight for weight, _ in MIX.values()]
    async with httpx.AsyncClient(base_url=url, headers=headers, timeout=60) as http:
        for _ in range(COMMANDS_PER_CLIENT):
            command = rng.choices(names, weights)[0]
            response = await http.post(f"/{command}", json=MIX[command][1])
            retry_after = response.headers.get("retry-after")
            answers.append(Answer(command, response.status_code, body_of(response), retry_after))
            if response.status_code == 503:  # back off a little, less than Retry-After asks
                await asyncio.sleep(rng.uniform(0, BACKOFF_S))


async def poll_health(url: str, answers: list[Answer], done: asyncio.Event) -> list[HealthCheck]:
    """GET /health (open, no token) until `done`, noting how far the storm was each time."""
    checks = []
    async with httpx.AsyncClient(base_url=url, timeout=60) as http:
        while not done.is_set():
            status = (await http.get("/health")).status_code
            checks.append(HealthCheck(status, len(answers)))
            await asyncio.sleep(HEALTH_POLL_S)
    return checks


def reasonless(answer: Answer) -> str | None:
    """What is wrong with an answer's reason, or None if it carries one."""
    body = answer.body
    if not isinstance(body.get("message"), str) or not body["message"].strip():
        return "no message"
    if answer.status == 503:
        if answer.retry_after is None or body.get("retry_after") is None:
            return "503 without Retry-After"
        return None
    if not body.get("event_id"):
        return "no event_id"
    if body.get("accepted") is not (answer.status == 202):
        return "accepted does not match the status"
    if any(sign in body["message"] for sign in TROUBLE):
        return "the answer reports trouble in the server"
    return None


async def run_storm(rig: Rig) -> tuple[list[Answer], list[HealthCheck]]:
    """Every command's answer, in the order they came, and the health checks meanwhile."""
    url = str(rig.api.base_url)
    headers = dict(rig.api.headers)
    answers: list[Answer] = []
    done = asyncio.Event()
    poller = asyncio.create_task(poll_health(url, answers, done))
    try:
        await asyncio.gather(
            *(storm_client(url, headers, SEED + index, answers) for index in range(CLIENTS))
        )
    finally:
        done.set()
        health = await poller
    return answers, health


def assert_healthy_throughout(health: list[HealthCheck], commands: int) -> None:
    """Every health check answered 200, and no tenth of the storm went without one."""
    assert health and {check.status for check in health} == {200}, Counter(health)
    marks = [0, *(check.commands_answered for check in health), commands]
    longest = max(later - earlier for earlier, later in itertools.pairwise(marks))
    assert longest <= commands // 10, f"{longest} commands answered without a health answer"


async def assert_the_cell_still_works(rig: Rig) -> None:
    """E-stop, reset, IDLE, then one spray run to the end."""
    estop = await rig.api.post("/estop", json={"reason": "after the storm"})
    assert estop.status_code == 202, estop.text
    assert estop.json()["state"] == "ERROR"
    reset = await rig.reset()
    assert reset.status_code == 202, reset.text
    await rig.wait_state("IDLE")
    await rig.start_spraying()
    snapshot = await rig.wait_state("IDLE", timeout=30)
    assert snapshot["operation_result"], snapshot
    assert not rig.glue.valve_open


def assert_one_continuous_story(journal: Path) -> None:
    """Every journaled transition is in the table and starts where the last one ended."""
    assert invalid_transitions(journal) == []
    transitions = journaled_transitions(journal)
    assert transitions, "nothing was journaled"
    assert transitions[0][0] == "INITIALIZING", transitions[0]
    breaks = [
        (before, after)
        for before, after in itertools.pairwise(transitions)
        if before[2] != after[0]
    ]
    assert breaks == [], f"transitions missing between: {breaks[:5]}"


async def test_a_storm_of_mixed_commands_gets_documented_answers_and_a_sound_journal(
    tmp_path: Path,
) -> None:
    async with open_rig(tmp_path, event_queue_size=QUEUE_SIZE) as rig:
        answers, health = await run_storm(rig)
        await assert_the_cell_still_works(rig)
        journal = rig.cell.journal.path

    statuses = Counter(answer.status for answer in answers)
    print(f"storm: {len(answers)} commands, {dict(statuses)}, {len(health)} health checks")
    unexpected = [a for a in answers if a.status not in ANSWERS]
    assert unexpected == [], f"{len(unexpected)} undocumented answers, e.g. {unexpected[:3]}"
    assert set(statuses) >= ANSWERS, f"not every path was exercised: {dict(statuses)}"
    without_reason = [(a, why) for a in answers if (why := reasonless(a))]
    assert without_reason == [], f"answers without a reason: {without_reason[:3]}"
    assert_healthy_throughout(health, len(answers))
    # The journal, complete now that the server has stopped.
    assert_one_continuous_story(journal)
    answered = {a.body["event_id"] for a in answers if a.status in (202, 409)}
    assert missing_events(journal, answered) == set()
