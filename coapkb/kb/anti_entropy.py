"""Anti-entropy: the rounds that find what a holder missed, the catch-up
at a start, and the compaction of the journal they allow.

At a start the robot asks every holder of every module at once (it missed
everything while it was down); then every ``sync_every_s`` (with jitter)
it sends one holder per module its causal context, round robin (the next
if that one does not answer, a standby if none does), and gets back what
it lacks; what the holder lacks of this robot's is pushed right after.
Each round ends with compaction: a delta every holder's context of a
round ago holds leaves the journal.  A robot kept in memory whose
catch-up heard every holder in full then raises its life's fence at each
and reads it again, and writes on under its lives' one name
(:mod:`.life_fence`).  Overview: :mod:`.replication`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random

from .. import clock
from ..model.deltas import CausalContext
from ..wire.sync import SyncMessage
from .life_fence import lives_writer
from .live import LiveKB
from .replication_settings import Holder, ReplicationSettings, ReplicationStats
from .sync_client import SyncClient

__all__ = ["MAX_FOLLOW_UPS", "AntiEntropy"]

log = logging.getLogger(__name__)

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
        each sent it all).  Then, for a robot kept in memory that heard
        them all in full, the name of its lives (:meth:`_take_lives_name`)."""
        if await self._hear(self.holders, standby_if_none=True) and self._may_take_lives_name():
            await self._take_lives_name()

    async def _hear(self, holders: dict[str, list[Holder]], *, standby_if_none: bool = False) -> bool:
        """One exchange with each of ``holders`` (module -> robots), the
        modules at once: whether each answered with nothing this robot
        lacks after; ``standby_if_none``: a module none answered for is
        asked of a standby."""

        async def module(name: str, holders: list[Holder]) -> bool:
            replica = self.live.replicas[name]
            heard = []
            for holder in holders:
                answer = await self._exchange(holder, name)
                heard.append(answer is not None and replica.context.covers(answer.context))
            if standby_if_none and not any(heard):
                await self._sync_with_a_standby(name)
            return all(heard)

        return all(await asyncio.gather(*(module(name, robots) for name, robots in holders.items())))

    def _may_take_lives_name(self) -> bool:
        """Kept in memory (a data folder's writer is for good) and not written yet."""
        return self.live.keeper is None and not self.live.has_written

    async def _take_lives_name(self) -> None:
        """A new life above every one the holders know of this robot: its
        fence raised at each holder, each read again in full after, and,
        if all were, the name of the robot's lives taken.  Every dot of an
        earlier life a holder will ever take is then here: the fence
        refuses those still on their way."""
        robot = self.outgoing.access.me
        fence = self.outgoing.fence
        life = fence.begin(robot)
        # Every robot this one sends its dots to: its holders and standbys.
        # A holder of another cluster takes them only from those.
        sent_to = {module: holders + self.standbys.get(module, []) for module, holders in self.holders.items()}
        heard = await self._hear(sent_to)
        if not heard or self.live.has_written:
            # Not heard: writes on under this life's own name, carrying no life.
            # Written meanwhile: its dot stands under that name.
            fence.own = None
            log.info("%s: not every holder read again after life %d's fence: writing on as %s", robot,
                     life.number, self.live.writer)
            return
        writer = lives_writer(robot)
        self.live.continue_as(writer)
        log.info("%s: life %d, every holder heard after its fence: writing as %s", robot, life.number, writer)

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
        return await self._exchange(holder, module) is not None

    async def _exchange(self, holder: Holder, module: str) -> SyncMessage | None:
        """One exchange with ``holder`` (and its follow-ups): its last answer."""
        replica = self.live.replicas[module]
        answer = await self.outgoing.exchange(holder, SyncMessage(module, replica.context.copy()))
        # An answer holds at most max_answer_bytes of changes: ask again at
        # once while the holder has more (it said so with its context).
        for _ in range(MAX_FOLLOW_UPS):
            if answer is None or replica.context.covers(answer.context):
                break
            answer = await self.outgoing.exchange(holder, SyncMessage(module, replica.context.copy()))
        if answer is None:
            return None
        # Both ways: what the holder lacks of ours, pushed now.
        theirs = replica.missing_for(answer.context)
        if theirs:
            await self.outgoing.push(holder, module, self.outgoing.fit(theirs) if isinstance(theirs, list) else theirs)
        return answer

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
