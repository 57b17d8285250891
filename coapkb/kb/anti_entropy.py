"""Anti-entropy: the rounds that find what a holder missed, the catch-up
at a start, and the compaction of the journal they allow.

At a start the robot asks every holder of every module at once (it missed
everything while it was down); then every ``sync_every_s`` (with jitter)
it sends one holder per module its causal context, round robin (the next
if that one does not answer, a standby if none does), and gets back what
it lacks; what the holder lacks of this robot's is pushed right after.
Each round ends with compaction: a delta every holder's context of a
round ago holds leaves the journal.  Overview: :mod:`.replication`.
"""

from __future__ import annotations

import asyncio
import contextlib
import random

from .. import clock
from ..model.deltas import CausalContext
from ..wire.sync import SyncMessage
from .live import LiveKB
from .replication_settings import Holder, ReplicationSettings, ReplicationStats
from .sync_client import SyncClient

__all__ = ["MAX_FOLLOW_UPS", "AntiEntropy"]

#: Exchanges one catch-up may chain while the holder has more to send.
MAX_FOLLOW_UPS = 1000


class AntiEntropy:
    """One robot's anti-entropy (see the module docstring); ``holders``:
    module -> the holders it syncs with; ``rng``: the rounds' jitter."""

    def __init__(self, live: LiveKB, holders: dict[str, list[Holder]], outgoing: SyncClient,
                 settings: ReplicationSettings, stats: ReplicationStats, rng: random.Random,
                 standbys: dict[str, list[Holder]] | None = None) -> None:
        self.live = live
        self.holders = holders
        self.standbys = standbys or {}
        self.outgoing = outgoing
        self.settings = settings
        self.stats = stats
        self._rng = rng
        #: The outgoing side's known contexts as they were at the last round (what compaction goes by).
        self._known_then: dict[tuple[str, str], CausalContext] = {}
        self._turn = 0
        #: Set once the catch-up at start has asked every holder (or there is none).
        self._caught_up = asyncio.Event()
        self._started_at: float | None = None
        #: The rounds, once started.
        self.task: asyncio.Task[None] | None = None

    def start(self) -> None:
        self._started_at = clock.monotonic()
        if any(self.holders.values()):
            self.task = asyncio.ensure_future(self._rounds())
        else:
            self._caught_up.set()

    @property
    def catching_up(self) -> bool:
        """The catch-up at start has begun and not ended."""
        return self._started_at is not None and not self._caught_up.is_set()

    async def caught_up(self) -> None:
        """Until the catch-up at start has asked every holder, at most
        :attr:`ReplicationSettings.read_after_catch_up_s` after it began."""
        if self._caught_up.is_set() or self._started_at is None:
            return
        left = self._started_at + self.settings.read_after_catch_up_s - clock.monotonic()
        if left > 0:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(left):
                    await self._caught_up.wait()

    async def _rounds(self) -> None:
        # A robot that starts (again) has missed everything: it catches up
        # from every holder at once, not at its first round.
        try:
            await self.catch_up()
        finally:
            self._caught_up.set()
        period = self.settings.sync_every_s
        while True:
            await asyncio.sleep(period * self._rng.uniform(2 / 3, 4 / 3))
            await self.sync_once()
            self.compact()

    async def catch_up(self) -> None:
        """One exchange with every holder of every module: the modules at
        once, their holders one after another (the first sends what was
        missed, the next only what the first lacked: asked all at once,
        each sent it all)."""

        async def module(name: str, holders: list[Holder]) -> None:
            answered = [await self._sync_with(holder, name) for holder in holders]
            if not any(answered):
                await self._sync_with_a_standby(name)

        await asyncio.gather(*(module(name, holders) for name, holders in self.holders.items()))

    async def sync_once(self) -> None:
        """One anti-entropy exchange per module, with its next holder; if
        it does not answer, with the others in turn, then the standbys,
        until one does."""
        self.stats.rounds += 1
        self._turn += 1
        for module, holders in self.holders.items():
            turn = self._turn % len(holders) if holders else 0
            for holder in holders[turn:] + holders[:turn]:
                if await self._sync_with(holder, module):
                    break
            else:
                await self._sync_with_a_standby(module)

    async def _sync_with_a_standby(self, module: str) -> None:
        """One exchange with the first standby of ``module`` that answers.
        Found in the simulator (seed 110 of nine robots with power cuts and
        forged syncs): a robot whose only holders of a module were its
        teammate and the next cluster's robot, both killed, never had that
        module's later writes again."""
        for holder in self.standbys.get(module, ()):
            if await self._sync_with(holder, module):
                return

    async def _sync_with(self, holder: Holder, module: str) -> bool:
        """One exchange with ``holder`` (and its follow-ups): whether it answered."""
        replica = self.live.replicas[module]
        answer = await self.outgoing.exchange(holder, SyncMessage(module, replica.context.copy()))
        # An answer holds at most max_answer_bytes of changes: ask again at
        # once while the holder has more (it said so with its context).
        for _ in range(MAX_FOLLOW_UPS):
            if answer is None or replica.context.covers(answer.context):
                break
            answer = await self.outgoing.exchange(holder, SyncMessage(module, replica.context.copy()))
        if answer is None:
            return False
        # Both ways: what the holder lacks of ours, pushed now.
        theirs = replica.missing_for(answer.context)
        if theirs:
            await self.outgoing.push(holder, module, self.outgoing.fit(theirs) if isinstance(theirs, list) else theirs)
        return True

    def compact(self) -> None:
        """Forget the deltas every holder had a round ago (each round ends
        with this).  Not by the contexts just heard: a holder's message
        sent before its latest (a push overtaken by the next, a question
        held up by retransmissions) asks with an older context, and a delta
        forgotten meanwhile made the answer a whole state (100 kB and more,
        several a minute, found on a long shift)."""
        for module, holders in self.holders.items():
            contexts = [self._known_then.get((module, h.name)) for h in holders]
            if holders and all(c is not None for c in contexts):
                self.live.replicas[module].compact(c for c in contexts if c is not None)
        self._known_then = dict(self.outgoing.known)
