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
from collections import OrderedDict
from typing import Awaitable, Callable

from ..transport.messages import Response


class AnswerCache:
    """A bounded LRU of successful answers, plus single flight per key."""

    def __init__(self, max_entries: int = 4096, max_bytes: int = 16 * 1024 * 1024) -> None:
        self.max_entries = max_entries
        self.max_bytes = max_bytes
        self._answers: OrderedDict[bytes, Response] = OrderedDict()
        self._bytes = 0
        self._running: dict[bytes, asyncio.Future[Response]] = {}
        self.hits = 0
        self.joined = 0
        self.misses = 0

    async def get_or_compute(self, key: bytes, compute: Callable[[], Awaitable[Response]]) -> Response:
        answer = self._answers.get(key)
        if answer is not None:
            self._answers.move_to_end(key)
            self.hits += 1
            return answer
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
        if size > self.max_bytes:
            return
        self._answers[key] = answer
        self._bytes += size
        while len(self._answers) > self.max_entries or self._bytes > self.max_bytes:
            _, old = self._answers.popitem(last=False)
            self._bytes -= len(old.payload)
