"""Whether the feeder itself is cut off from its robots.

The fault model has at most one robot of a cluster out (dead, frozen or cut
off) at a time, and the feeder may be cut off from every robot for a while.
So silence from every robot of every cluster at once is the feeder's own
link, not their deaths.  A feeder that declared them all down for it gave the
run up ("every robot of cluster 3 is down"; found in the simulator, the
feeder cut off for 10 s).  Instead it declares nobody down, and its waits go
on, each within its own bound (a task's timeout), while its watcher keeps
asking and observing the robots: the first answer resumes the run.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging

from .. import clock
from ..agent.observed_states import ObservedStates, indirect_probe
from ..agent.robot_state import RobotState
from ..transport.base import ClientTransport, PeerGone, TransportError
from ..transport.messages import Request
from .roster import Roster

log = logging.getLogger(__name__)

#: While the feeder is cut off, it asks every robot again one request
#: timeout after it last found nobody answering, then twice as long each
#: time, up to this many request timeouts: the longest it may take, once the
#: link is back, to find so.  A state that reaches the feeder meanwhile (an
#: observation) ends the wait at once.
MAX_BACKOFF_TIMEOUTS = 8


class Reach:
    """Confirms the feeder's suspicions of its robots (the watcher's
    ``confirm_silence``), telling "I am cut off" from "it is down"."""

    def __init__(self, client: ClientTransport, watcher: ObservedStates, roster: Roster, ask: Request) -> None:
        self._client = client
        self._watcher = watcher
        self._roster = roster
        #: What each robot is asked (a plain GET of its state).
        self._ask = ask
        #: The round of requests in progress (:meth:`answering`), shared.
        self._round: asyncio.Future[frozenset[str] | None] | None = None
        #: Since when the feeder has found itself cut off (None: it reaches its robots).
        self.cut_off_since: float | None = None
        self._backoff_s = 0.0
        #: Set when a robot's state reached the feeder since it found itself cut off.
        self._heard = asyncio.Event()

    async def silent_to_the_feeder_only(self, robot_id: str) -> bool:
        """Whether ``robot_id``'s silence is not the robot's own, so that it
        is not declared down: a teammate of its reaches it (SWIM's indirect
        probe), or, asked again with every other robot, it answers now or
        none of them does.  The robot's own answer counts: failures counted
        while the feeder was cut off end in this question after the link is
        back, and must not declare a live robot down then.  While the feeder
        is cut off, the question waits for the next round of asking (with
        backoff), and so do the watcher's liveness requests that raised it."""
        watcher = self._watcher
        if self.cut_off_since is None:
            helpers = [self._roster.endpoints[r] for r in self._roster.cluster_of(robot_id)
                       if r != robot_id and r not in watcher.down]
            if await indirect_probe(self._client, helpers, robot_id, watcher.request_timeout_s):
                return True
        answering = await self.answering()
        return answering is None or robot_id in answering

    def heard_from(self, robot_id: str, state: RobotState) -> None:
        """A robot's state reached the feeder (a watcher listener): ask again now."""
        self._heard.set()

    async def answering(self) -> frozenset[str] | None:
        """The robots the feeder counts on that answer it now (each asked
        once, at once; the network's "nobody listens there" counts as an
        answer: the link works); None if none does: the feeder is cut off.
        An empty set when nobody is left to ask.  Concurrent callers share
        one round; while the feeder is cut off, a round starts after the
        backoff."""
        running = self._round
        if running is None or running.done():
            running = self._round = asyncio.ensure_future(self._ask_everyone())
        return await asyncio.shield(running)

    async def _ask_everyone(self) -> frozenset[str] | None:
        watcher = self._watcher
        if self.cut_off_since is not None:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(self._backoff_s):
                    await self._heard.wait()
        asked = [r for r in self._roster.robot_ids if r not in watcher.down]
        timeout = watcher.request_timeout_s

        async def answers(robot_id: str) -> bool:
            try:
                await self._client.request(self._roster.endpoints[robot_id], self._ask, timeout=timeout)
            except PeerGone:
                return True
            except TransportError:
                return False
            return True

        answered = await asyncio.gather(*(answers(r) for r in asked))
        if asked and not any(answered):
            if self.cut_off_since is None:
                self.cut_off_since = clock.monotonic()
                self._backoff_s = timeout
                log.warning("the feeder reaches none of its robots: it is cut off itself, declares nobody down "
                            "and asks again with backoff")
            else:
                self._backoff_s = min(2 * self._backoff_s, MAX_BACKOFF_TIMEOUTS * timeout)
            self._heard.clear()
            return None
        if self.cut_off_since is not None:
            log.warning("the feeder reaches its robots again after %.1f s cut off",
                        clock.monotonic() - self.cut_off_since)
            self.cut_off_since = None
        return frozenset(r for r, yes in zip(asked, answered) if yes)
