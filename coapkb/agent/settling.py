"""How a robot's decision is made to match its teammates' when it cannot
stand alone: its own knowledge did not arrive (a lost answer, a holder
that seemed down), or it may be behind them (frozen, or its teammates
already past the task).  It takes a teammate's decision whole, decided on
knowledge first, so every robot of the cluster decides a task alike
(docs/failover.md)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable, Mapping, MutableMapping
from dataclasses import dataclass, field

from .. import clock
from ..transport.base import PeerGone, TransportError
from .decisions import DecisionMessage, Task
from .robot_state import Decision
from .team_membership import Membership
from .team_view import TeamView

log = logging.getLogger(__name__)

#: How often a robot whose knowledge did not arrive asks its teammates again.
SETTLE_POLL_S = 0.5
#: How long it asks, in query timeouts; and while a teammate answers that it
#: is still deciding the task, how long at most.
SETTLE_WAIT_TIMEOUTS = 2
SETTLE_DECIDING_TIMEOUTS = 6

#: Asks a teammate for its decision on a task (None: it has none yet;
#: TransportError: it does not answer).
AskDecision = Callable[[str, int], Awaitable[DecisionMessage | None]]
#: Why no majority of the cluster grants this robot a lease now, or None.
Fenced = Callable[[], Awaitable[str | None]]


@dataclass
class _Round:
    """What one round of asking the teammates told."""

    #: Teammates that cannot help: failed the same way, gone, or decided without this robot.
    failed: int = 0
    #: A teammate answered that it is still deciding (or its answer may be stale).
    deciding: bool = False
    #: A teammate that is up did not answer.
    unanswered: bool = False
    #: Decisions on knowledge, by teammate.
    known: list[tuple[str, DecisionMessage]] = field(default_factory=list)


class Settler:
    """One robot's side of settling decisions with its teammates."""

    def __init__(self, robot_id: str, team: TeamView, query_timeout_s: float, ask_decision: AskDecision | None,
                 recent: MutableMapping[int, DecisionMessage], *, fenced: Fenced | None = None) -> None:
        self.robot_id = robot_id
        self.team = team
        self._query_timeout_s = query_timeout_s
        self._ask_decision = ask_decision
        #: The robot's decisions as teammates asking it get them (its Controller's).
        self.recent = recent
        self._fenced = fenced

    async def settle(self, task: Task, alone: DecisionMessage) -> DecisionMessage:
        """The decision on ``task`` when this robot's own knowledge did not
        arrive (a lost answer, a holder that seemed down): a live teammate's
        decided on knowledge, taken whole, so every robot decides alike;
        ``alone`` (unavailable, or an error) if every live teammate failed
        too, or none decided within the wait (:data:`SETTLE_WAIT_TIMEOUTS`
        query timeouts, up to :data:`SETTLE_DECIDING_TIMEOUTS` while one
        answers that it has not decided yet).  Meanwhile teammates asking
        this robot get ``alone``: two robots that both failed do not wait
        for each other."""
        self.recent[task.seq] = alone
        if self._ask_decision is None:
            return alone
        started = clock.monotonic()
        deadline = started + self._query_timeout_s * SETTLE_WAIT_TIMEOUTS
        last_call = started + self._query_timeout_s * SETTLE_DECIDING_TIMEOUTS
        deciding = unanswered = False
        # Past the deadline only while a teammate says it is still deciding,
        # or while one that is up has not answered yet: a round can end past
        # the deadline (a frozen teammate's ask runs out, then the indirect
        # probe that finds it back), and ending there would decide alone
        # against a teammate that, asked by it meanwhile, saw this robot's
        # undecided answer and decided on its own knowledge (found in the
        # simulator: a robot frozen 14-17 s, the only holder of a module).
        while clock.monotonic() < (last_call if deciding or unanswered else deadline):
            # A teammate whose answer was just lost is asked too: it may be the
            # one that had the knowledge (found in the simulator).  A robot
            # with no majority up asks the members it has down as well: it may
            # be the one that was cut off, and they went on counting it (found
            # in the simulator: after the heal it decided every task alone
            # while they assigned it tasks).  One that answers is counted on again.
            outnumbered = self.team.membership.alone
            # With nobody up to ask, the members it has down are asked, as
            # when outnumbered (found in the simulator, seed 15717: a robot
            # that had left a dead teammate out found the other, back from
            # a partition, down after the heal, and decided nothing on
            # every later task without asking it once).
            others = self._others()
            mates = [r for r in others if outnumbered or self.team.is_up(r)] or others
            timed = await asyncio.gather(*(self._ask_timed(mate, task.seq) for mate in mates))
            round_end = clock.monotonic()
            heard = [mate for mate, (theirs, _) in zip(mates, timed)
                     if not isinstance(theirs, BaseException) and not self.team.is_up(mate)]
            if heard:
                await asyncio.gather(*(self.team.revival.heard_again(mate) for mate in heard))
            judged = await self._judge(task, dict(zip(mates, timed)), round_end, outnumbered)
            deciding, unanswered, known = judged.deciding, judged.unanswered, judged.known
            if known:
                mate, theirs = _preferred(known)
                return self._take(task, theirs, f"its knowledge did not reach this robot; took {mate}'s decision")
            if judged.failed == len(mates):  # nobody had the knowledge: every robot alike
                return alone
            await asyncio.sleep(SETTLE_POLL_S)
        return alone

    async def _judge(self, task: Task, answers: Mapping[str, tuple[DecisionMessage | None | BaseException, float]],
                     round_end: float, outnumbered: bool) -> _Round:
        """What one round of asking, ended at ``round_end``, told: each
        teammate's answer (or its failure) on ``task`` and when it came."""
        judged = _Round()
        for mate, (theirs, answered_at) in answers.items():
            if isinstance(theirs, BaseException):
                # A lost answer is asked again (found in the simulator:
                # three asks lost at 20 % loss, and this robot decided
                # alone); the failure counts like a probe's, so a dead
                # teammate is soon known down, and cannot help.
                if isinstance(theirs, TransportError):
                    await self.team.request_failed(mate, theirs)
                # Outnumbered, a silence is no answer: the silent ones may
                # be the majority, cut off from this robot, and it waits
                # for them; only a teammate whose process is gone cannot help.
                # Outnumbered by this very failure counts too (simulator seed
                # 54708: the one silent teammate, cut off with the knowledge,
                # was found down in the round, counted as failed, and the
                # robot decided alone against its decision).
                outnumbered = outnumbered or self.team.membership.alone
                gone = not self.team.is_up(mate) and (not outnumbered or isinstance(theirs, PeerGone))
                judged.failed += gone
                judged.unanswered = judged.unanswered or not gone
            elif theirs is None or theirs.decision.object != task.object:
                # Still deciding: waited for past the deadline (found in
                # the simulator: a robot gave up the moment before a
                # teammate back from a partition decided on knowledge).
                judged.deciding = True
            elif not theirs.decision.members and round_end - answered_at > SETTLE_POLL_S:
                # Its settling, answered long before this round ended (the
                # round waited on a silent teammate): it may have decided
                # on knowledge since, so it is asked again (found in the
                # simulator, seed 7862: an answer 15 s old ended a
                # settling that the teammate's decision would have changed).
                judged.deciding = True
            elif not self.counts_me(theirs.decision):
                # Decided in a membership without this robot: not taken
                # (it would name their epoch, and its next decisions,
                # its own, would then not be void).
                judged.failed += 1
            elif theirs.decision.error is None and theirs.decision.unavailable is None:
                judged.known.append((mate, theirs))
            else:
                judged.failed += 1
        return judged

    async def _ask_timed(self, mate: str, seq: int) -> tuple[DecisionMessage | None | BaseException, float]:
        """``mate``'s answer (or its failure) on task ``seq``, and when it came."""
        assert self._ask_decision is not None
        try:
            answer: DecisionMessage | None | BaseException = await self._ask_decision(mate, seq)
        except Exception as exc:  # noqa: BLE001 - judged by the caller, like gather's return_exceptions
            answer = exc
        return answer, clock.monotonic()

    async def decided_before(self, task: Task, received: float) -> DecisionMessage | None:
        """A teammate's decision on ``task`` if one may have decided it before
        this robot began it: its observed plan is past the task already, or
        this process stood still for a request timeout or more since about
        when the task came (its teammates' requests to it went unanswered
        meanwhile, and the observations of their plans may have been dropped).
        This robot lags behind, and what it would compute now may not be what
        they settled.  Found in the simulator: a robot frozen in a pick for
        20 s, the one the Location KB's places are read from, while its
        teammates settled a task unavailable without it; back, it decided the
        task alone on its own knowledge and picked it, and the record said
        failed.  The decision is taken whole, as :meth:`settle` takes one:
        one decided on knowledge first, else one settled unavailable (and
        applied); none decided in a membership without this robot (its own
        decision is void then).  A robot in step asks nothing: no extra
        message per task."""
        mates = [r for r in self._others() if self.team.is_up(r)]
        window = clock.monotonic() - received + self._query_timeout_s * 2
        stalled = self.team.stalled_within(window) >= self.team.request_timeout_s
        if not stalled:
            ahead = [r for r in mates if (state := self.team.state_of(r)) is not None and state.plan.seq >= task.seq]
            return await self._taken_from(task, ahead, "decided it before this robot began")
        if (taken := await self._taken_from(task, mates, "decided it before this robot began")) is not None:
            return taken
        return await self._awaited_if_fenced(task, mates)

    async def leaders_decision(self, task: Task, leader: str) -> DecisionMessage | None:
        """The decision on ``task`` that ``leader``, found down, sent another
        follower ("compute and communicate"), taken whole with its
        membership.  Computed here instead, without the leader's plan, it
        was taken in a membership without the leader, while the follower
        that had the decision named one with it (simulator, seed 2026 of the
        compute-and-communicate swarm profile: one task in two epochs)."""
        mates = [r for r in self._others() if r != leader and self.team.is_up(r)]
        return await self._taken_from(task, mates, f"had the decision {leader} sent")

    async def _awaited_if_fenced(self, task: Task, mates: list[str]) -> DecisionMessage | None:
        """After a stall, with no teammate's decision on ``task`` yet: if no
        majority grants this robot a lease any more, its teammates have it
        down and decide without it, and would never take a decision of its
        own; it waits for theirs (asking every :data:`SETTLE_POLL_S`, for
        twice the longest settling), then decides alone.  It stops waiting
        once one decided in a membership without it (its own decision is
        void then), or is past the task and no longer keeps its decision.
        Found in the simulator, seed 43737: the holder of the Location KB
        frozen 4-24 s; back, it found its teammates still settling the task
        it held, decided it on its own knowledge, and they settled it
        unavailable.  None while it is still granted: teammates that count
        it take its decision on knowledge as they settle."""
        if self._fenced is None or not mates:
            return None
        try:
            async with asyncio.timeout(self._query_timeout_s):
                why = await self._fenced()
        except TimeoutError:  # cut off: neither granted nor refused
            return None
        if why is None:
            return None
        log.warning("task %d (%s): this robot stood still and is fenced (%s): it waits for its teammates' decision",
                    task.seq, task.object, why)
        deadline = clock.monotonic() + self._query_timeout_s * SETTLE_DECIDING_TIMEOUTS * 2
        while clock.monotonic() < deadline:
            await asyncio.sleep(SETTLE_POLL_S)
            answers = await self._answers(task, mates)
            if (taken := self._chosen(task, mates, answers, "decided it while this robot was fenced")) is not None:
                return taken
            if any(isinstance(a, DecisionMessage) and not self.counts_me(a.decision) for a in answers):
                return None  # left out: this robot's own decision is void, whatever it is
            if any(a is None and (state := self.team.state_of(mate)) is not None and state.plan.seq >= task.seq
                   for mate, a in zip(mates, answers)):
                return None  # past the task, and its decision no longer kept: none will come
        log.warning("task %d (%s): no teammate decided it meanwhile: decided alone", task.seq, task.object)
        return None

    async def decided_by_teammates(self, task: Task) -> DecisionMessage | None:
        """A live teammate's decision on ``task`` already made, before this
        robot, which settled it unavailable, decides it again on another
        holder's knowledge: a teammate that ended its settling meanwhile
        and applied the task unavailable is followed, not contradicted.
        While this robot decides again, teammates asking it are told it is
        still deciding, so one still settling waits for its decision rather
        than end on its unavailable answer (found in the simulator, seed
        7862: a starved teammate ended its settling on both teammates'
        unavailable answers the moment before one of them decided again)."""
        self.recent.pop(task.seq, None)
        if self._ask_decision is None:
            return None
        return await self._taken_from(task, [r for r in self._others() if self.team.is_up(r)], "decided it already")

    async def _taken_from(self, task: Task, mates: list[str], how: str) -> DecisionMessage | None:
        """The decision on ``task`` of one of ``mates``, taken whole as
        :meth:`settle` takes one: decided on knowledge first, else settled
        unavailable and applied; none decided in a membership without this
        robot."""
        return self._chosen(task, mates, await self._answers(task, mates), how)

    async def _answers(self, task: Task, mates: list[str]) -> list[DecisionMessage | None | BaseException]:
        if not mates or self._ask_decision is None:
            return []
        return await asyncio.gather(*(self._ask_decision(mate, task.seq) for mate in mates), return_exceptions=True)

    def _chosen(self, task: Task, mates: list[str], answers: list[DecisionMessage | None | BaseException],
                how: str) -> DecisionMessage | None:
        # An unavailable one still being settled (not yet applied, so not
        # stamped with its members) may yet give way to a decision on knowledge.
        taken = [(mate, theirs) for mate, theirs in zip(mates, answers)
                 if isinstance(theirs, DecisionMessage) and theirs.decision.object == task.object
                 and theirs.decision.error is None and self.counts_me(theirs.decision)
                 and (theirs.decision.unavailable is None or theirs.decision.members)]
        if not taken:
            return None
        mate, theirs = _preferred(taken)
        return self._take(task, theirs, f"{mate} {how}; took its decision")

    def _take(self, task: Task, theirs: DecisionMessage, said: str) -> DecisionMessage:
        """Take a teammate's decision whole, and the membership it was taken
        in: this robot's own view may not have caught up (it computed
        nothing), and the next join counts its epoch from there (found in
        the simulator)."""
        log.warning("task %d (%s): %s", task.seq, task.object, said)
        self.team.membership.adopt(Membership(theirs.decision.epoch, theirs.decision.members), task.seq)
        return theirs

    def _others(self) -> list[str]:
        """The members of this robot's membership but itself."""
        return [r for r in self.team.membership.members if r != self.robot_id]

    def counts_me(self, decision: Decision) -> bool:
        """Whether ``decision`` was taken in a membership with this robot in it."""
        return not decision.members or self.robot_id in decision.members


def _preferred(decisions: list[tuple[str, DecisionMessage]]) -> tuple[str, DecisionMessage]:
    """The teammate's decision to take of ``decisions``: one on knowledge
    first, then the one in the newest membership, a decision in an older
    one being void if the newer left its robot out (found in the simulator,
    seed 11774: a robot back from a freeze decided in the membership it had
    left, a teammate had excluded it meanwhile, and the third, lagging,
    took the frozen one's decision); the first asked among equals."""
    return min(decisions, key=lambda item: (item[1].decision.unavailable is not None, -item[1].decision.epoch))
