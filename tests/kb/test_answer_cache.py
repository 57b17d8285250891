"""The answer cache (coapkb.kb.answer_cache): least recently used answers go
first, by count and by bytes; errors and oversized answers are never kept;
copies of a question asked while it runs share one run."""

from __future__ import annotations

import asyncio

import pytest

from coapkb.kb.answer_cache import AnswerCache
from coapkb.transport.messages import Response, Status


class Answers:
    """A query that answers ``key`` with ``size`` bytes and counts its runs per key."""

    def __init__(self) -> None:
        self.runs: dict[bytes, int] = {}

    def compute(self, key: bytes, size: int = 4, status: Status = Status.CONTENT):  # type: ignore[no-untyped-def]
        async def run() -> Response:
            self.runs[key] = self.runs.get(key, 0) + 1
            return Response(status, key[:1] * size)

        return run

    async def ask(self, cache: AnswerCache, *keys: bytes, size: int = 4) -> None:
        for key in keys:
            answer = await cache.get_or_compute(key, self.compute(key, size))
            assert answer.payload == key[:1] * size


async def test_the_least_recently_used_answer_goes_first_when_entries_run_out() -> None:
    cache, answers = AnswerCache(max_entries=2), Answers()
    await answers.ask(cache, b"a", b"b", b"a", b"c")  # a was used after b: b goes
    assert answers.runs == {b"a": 1, b"b": 1, b"c": 1}
    await answers.ask(cache, b"a", b"c")
    assert answers.runs == {b"a": 1, b"b": 1, b"c": 1} and cache.hits == 3
    await answers.ask(cache, b"b")  # evicted: runs again, and now a goes (c was used since)
    await answers.ask(cache, b"c")
    assert answers.runs == {b"a": 1, b"b": 2, b"c": 1}
    await answers.ask(cache, b"a")
    assert answers.runs == {b"a": 2, b"b": 2, b"c": 1}
    assert (cache.hits, cache.misses) == (4, 5)


async def test_answers_are_evicted_by_bytes_too() -> None:
    cache, answers = AnswerCache(max_entries=100, max_bytes=10), Answers()
    await answers.ask(cache, b"a", b"b", size=4)  # 8 bytes: both fit
    await answers.ask(cache, b"c", size=4)  # 12 > 10: a goes
    await answers.ask(cache, b"b", b"c", size=4)
    assert answers.runs == {b"a": 1, b"b": 1, b"c": 1}
    await answers.ask(cache, b"d", size=10)  # fills the cache alone: b and c go
    await answers.ask(cache, b"d", size=10)
    assert answers.runs[b"d"] == 1
    await answers.ask(cache, b"b", b"c", size=4)
    assert answers.runs == {b"a": 1, b"b": 2, b"c": 2, b"d": 1}


async def test_an_answer_larger_than_the_cache_is_not_kept_and_evicts_nothing() -> None:
    cache, answers = AnswerCache(max_bytes=10), Answers()
    await answers.ask(cache, b"a", size=4)
    await answers.ask(cache, b"x", b"x", size=11)
    await answers.ask(cache, b"a", size=4)
    assert answers.runs == {b"a": 1, b"x": 2}


async def test_errors_are_not_kept() -> None:
    cache, answers = AnswerCache(), Answers()
    for _ in range(2):
        answer = await cache.get_or_compute(b"e", answers.compute(b"e", status=Status.NOT_FOUND))
        assert answer.status == Status.NOT_FOUND
    assert answers.runs == {b"e": 2} and cache.hits == 0


async def test_copies_asked_while_the_query_runs_share_its_run() -> None:
    cache, release, runs = AnswerCache(), asyncio.Event(), []

    async def slow() -> Response:
        runs.append(1)
        await release.wait()
        return Response(Status.CONTENT, b"answer")

    waiting = [asyncio.create_task(cache.get_or_compute(b"q", slow)) for _ in range(3)]
    while cache.joined < 2:  # the second and third copy found the run in progress
        await asyncio.sleep(0)
    release.set()
    assert [(await w).payload for w in waiting] == [b"answer"] * 3
    assert runs == [1] and (cache.misses, cache.joined) == (1, 2)


async def test_a_failed_run_fails_its_joiners_and_is_not_kept() -> None:
    cache, release = AnswerCache(), asyncio.Event()

    async def failing() -> Response:
        await release.wait()
        raise RuntimeError("store broke")

    first = asyncio.create_task(cache.get_or_compute(b"q", failing))
    await asyncio.sleep(0)
    second = asyncio.create_task(cache.get_or_compute(b"q", failing))
    while cache.joined < 1:
        await asyncio.sleep(0)
    release.set()
    for task in (first, second):
        with pytest.raises(RuntimeError, match="store broke"):
            await task
    answers = Answers()
    await answers.ask(cache, b"q")  # the next copy runs the query again
    assert answers.runs == {b"q": 1}


async def test_an_answer_nobody_asked_for_in_idle_s_goes() -> None:
    now = [0.0]
    cache, answers = AnswerCache(idle_s=600.0, clock=lambda: now[0]), Answers()
    await answers.ask(cache, b"a", b"b")
    now[0] = 400.0
    await answers.ask(cache, b"a")  # a used again: its age starts over
    now[0] = 700.0
    await answers.ask(cache, b"a", b"b")  # b idle for 700 s: gone; a idle 300 s: kept
    assert answers.runs == {b"a": 1, b"b": 2}
    assert cache.hits == 2
