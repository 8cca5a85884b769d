"""The lane the plant's interfaces wait on: no command answer in flight, or a bound."""

from __future__ import annotations

import asyncio

from server.core.infra.answers_in_flight import AnswersInFlight, after_answers


async def test_no_answer_in_flight_means_no_wait() -> None:
    answers = AnswersInFlight()
    await asyncio.wait_for(answers.none_pending(limit=60), 1)
    await after_answers(None)


async def test_waits_until_every_answer_has_gone() -> None:
    answers = AnswersInFlight()
    answers.begin()
    answers.begin()
    waiting = asyncio.create_task(answers.none_pending(limit=60))
    await asyncio.sleep(0)
    answers.end()
    await asyncio.sleep(0)
    assert not waiting.done() and answers.count == 1
    answers.end()
    await asyncio.wait_for(waiting, 1)
    assert answers.count == 0


async def test_a_stream_of_commands_does_not_hold_the_plant_for_ever() -> None:
    answers = AnswersInFlight()
    answers.begin()  # never ends
    await asyncio.wait_for(answers.none_pending(limit=0.01), 5)
    assert answers.count == 1
    answers.end()
    answers.end()  # one too many never goes below zero
    assert answers.count == 0
