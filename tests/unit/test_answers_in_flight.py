"""The lane the plant's interfaces wait on: the answers in flight when the wait began have
gone, or a bound."""

from __future__ import annotations

import asyncio

from server.core.infra.answers_in_flight import AnswersInFlight, after_answers


async def test_no_answer_in_flight_means_no_wait() -> None:
    answers = AnswersInFlight()
    await asyncio.wait_for(answers.none_pending(limit=60), 1)
    await after_answers(None)


async def test_waits_until_every_answer_in_flight_has_gone() -> None:
    answers = AnswersInFlight()
    first, second = answers.begin(), answers.begin()
    waiting = asyncio.create_task(answers.none_pending(limit=60))
    await asyncio.sleep(0)
    answers.end(first)
    await asyncio.sleep(0)
    assert not waiting.done() and answers.count == 1
    answers.end(second)
    await asyncio.wait_for(waiting, 1)
    assert answers.count == 0


async def test_a_command_that_arrives_during_the_wait_is_not_waited_for() -> None:
    """A stop's transition waits for the stop's answer, not for the reset sent after it."""
    answers = AnswersInFlight()
    stop = answers.begin()
    waiting = asyncio.create_task(answers.none_pending(limit=60))
    await asyncio.sleep(0)
    reset = answers.begin()  # arrives while the plant waits; answered much later
    answers.end(stop)
    await asyncio.wait_for(waiting, 1)
    assert answers.count == 1
    answers.end(reset)
    assert answers.count == 0


async def test_answers_ending_out_of_order_release_the_wait_once_all_have_gone() -> None:
    answers = AnswersInFlight()
    tickets = [answers.begin() for _ in range(3)]
    waiting = asyncio.create_task(answers.none_pending(limit=60))
    await asyncio.sleep(0)
    answers.end(tickets[2])
    answers.end(tickets[1])
    await asyncio.sleep(0)
    assert not waiting.done()
    answers.end(tickets[0])
    await asyncio.wait_for(waiting, 1)


async def test_a_stream_of_commands_does_not_hold_the_plant_for_ever() -> None:
    answers = AnswersInFlight()
    ticket = answers.begin()  # never ends
    await asyncio.wait_for(answers.none_pending(limit=0.01), 5)
    assert answers.count == 1
    answers.end(ticket)
    answers.end(ticket)  # ended twice: harmless
    assert answers.count == 0
