"""Answers of a read-only KB, kept by their ETag, and queries in progress.

The KB never changes while a robot runs, so an answer stays right for as
long as the KB's ETag does (which is part of the answer's ETag).  Two
things follow: a repeated question (a named query asked by every teammate
for every task, a retry of a request whose answer was lost on the radio)
is answered without running the query again, and a retry that arrives
while the first copy's query is still running waits for that run instead
of starting another.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

from ..clock import monotonic as loop_clock
from ..transport.expiring import ExpiringMap
from ..transport.messages import Response

#: Bounds of a robot's answer cache (docs/flood.md).  Anyone who can send a
#: query can fill it, so it must stay small beside the robot's ~70 MiB: a
#: named query's answer is 50-500 bytes, so 4 MiB holds every answer a
#: team asks for; what nobody asked for in ten minutes goes.
ANSWERS_KEPT = 4096
ANSWER_BYTES = 4 * 1024 * 1024
ANSWER_IDLE_S = 600.0


class AnswerCache:
    """A bounded LRU of successful answers, plus single flight per key."""

    def __init__(self, max_entries: int = ANSWERS_KEPT, max_bytes: int = ANSWER_BYTES,
                 idle_s: float = ANSWER_IDLE_S, clock: Callable[[], float] = loop_clock) -> None:
        #: key -> answer, least recently used out first.
        self._answers: ExpiringMap[bytes, Response] = ExpiringMap(
            idle_s, max_entries, max_bytes, lambda answer: len(answer.payload), clock)
        self._running: dict[bytes, asyncio.Future[Response]] = {}
        self.hits = 0
        self.joined = 0
        self.misses = 0

    async def get_or_compute(self, key: bytes, compute: Callable[[], Awaitable[Response]]) -> Response:
        kept = self._answers.get(key)
        if kept is not None:
            self.hits += 1
            return kept
        running = self._running.get(key)
        if running is not None:
            self.joined += 1
            return await asyncio.shield(running)
        self.misses += 1
        future: asyncio.Future[Response] = asyncio.get_running_loop().create_future()
        self._running[key] = future
        try:
            answer = await compute()
        except BaseException as exc:
            future.set_exception(exc)
            future.exception()  # retrieved: nobody else may be waiting
            raise
        finally:
            del self._running[key]
        if not future.done():
            future.set_result(answer)
        if answer.status.is_success and key not in self._answers:
            self._answers[key] = answer  # (one larger than max_bytes is not kept)
        return answer
