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
import time
from collections import OrderedDict
from typing import Awaitable, Callable

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
                 idle_s: float = ANSWER_IDLE_S, clock: Callable[[], float] = time.monotonic) -> None:
        self.max_entries = max_entries
        self.max_bytes = max_bytes
        self.idle_s = idle_s
        self._clock = clock
        #: key -> (answer, last use), least recently used first.
        self._answers: OrderedDict[bytes, tuple[Response, float]] = OrderedDict()
        self._bytes = 0
        self._running: dict[bytes, asyncio.Future[Response]] = {}
        self.hits = 0
        self.joined = 0
        self.misses = 0

    async def get_or_compute(self, key: bytes, compute: Callable[[], Awaitable[Response]]) -> Response:
        now = self._purge()
        kept = self._answers.get(key)
        if kept is not None:
            self._answers[key] = (kept[0], now)
            self._answers.move_to_end(key)
            self.hits += 1
            return kept[0]
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
        if answer.status.is_success:
            self._store(key, answer)
        return answer

    def _store(self, key: bytes, answer: Response) -> None:
        size = len(answer.payload)
        if size > self.max_bytes or key in self._answers:
            return
        self._answers[key] = (answer, self._clock())
        self._bytes += size
        while len(self._answers) > self.max_entries or self._bytes > self.max_bytes:
            self._drop_oldest()

    def _purge(self) -> float:
        """Drop the answers unused for ``idle_s``; returns the clock's time."""
        now = self._clock()
        while self._answers and next(iter(self._answers.values()))[1] <= now - self.idle_s:
            self._drop_oldest()
        return now

    def _drop_oldest(self) -> None:
        _, (old, _) = self._answers.popitem(last=False)
        self._bytes -= len(old.payload)
