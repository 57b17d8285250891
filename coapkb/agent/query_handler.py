"""Query Handler (the seed's Fig. 2): each query goes to the KB that can answer it.

A query for a KB module this robot holds runs on its own knowledge base; any
other goes, through the transport interface, to a teammate holding that
module (or to the central server in the centralised baseline).  A module may
be held by several teammates (replicas): a dead or unreachable holder is
failed over to the next, and a slow one is hedged.
"""

from __future__ import annotations

import asyncio
import collections
import logging
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field

from .. import clock
from ..cancelling import cancel_and_wait
from ..config import RobotConfig, Teammate
from ..errors import CoapkbError
from ..kb.client import KBClient, QueryFailed, named_request
from ..kb.errors import KBError
from ..kb.live import LiveKB
from ..kb.named_queries import NAMED_QUERIES
from ..kb.store import KnowledgeBase
from ..model.results import QueryResult
from ..transport.base import Endpoint, TransportError
from ..transport.messages import ContentFormat, Method
from .fact_push import FactPusher, PushedFacts
from .task_assigner import robot_sort_key

log = logging.getLogger(__name__)

#: How queries travel: "compact" = named query resources with CBOR answers
#: (a few bytes each way); "seed" = the whole SPARQL text in every request
#: with SPARQL-JSON answers, as the seed paper's system did.
QUERY_WIRES = ("compact", "seed")
#: Facts' times from teammates a robot keeps for its statistics.
LATENCIES_KEPT = 16_384
#: Round trips of the latest queries that set the hedging delay and the wait for a push.
ROUND_TRIPS_KEPT = 64
#: How long a robot waits for a holder's pushed answer before it asks,
#: before it has measured a round trip; and the least it ever waits.
PUSH_WAIT_S = 0.5
PUSH_WAIT_FLOOR_S = 0.02
#: A fact from teammates later than this is logged (INFO): the tail, told fact by fact.
SLOW_FACT_S = 1.0


class QueryError(CoapkbError):
    """A query could not be answered; the message says which, where and why."""


class ModuleUnavailable(QueryError):
    """No holder of a KB module answers: all are known to be down or failed
    at the transport.  A task that needs the module cannot be done until one
    is back; the team records that and goes on with the other tasks."""

    def __init__(self, module: str, why: Mapping[str, str]) -> None:
        self.module = module
        self.why = dict(why)
        holders = "; ".join(f"{robot}: {reason}" for robot, reason in self.why.items())
        super().__init__(f"no live robot holds the {module} KB ({holders})")


@dataclass
class QueryStats:
    local: int = 0
    remote: int = 0
    failed: int = 0
    #: Remote answers served from the client's cache (fresh, or revalidated by ETag).
    cached: int = 0
    #: Queries re-sent to another holder of the module after a transport failure.
    failovers: int = 0
    #: Queries also sent to a second holder because the first was slow.
    hedged: int = 0
    #: Remote answers the holder pushed before they were asked (in ``cached`` too).
    pushed: int = 0
    #: Wall-clock time of the latest facts from teammates, in seconds, from
    #: when this robot needed each to when it had it (asked, or pushed and
    #: waited for): at most ``LATENCIES_KEPT`` (a robot runs for days: its
    #: statistics must not grow with them).
    remote_latencies: list[float] = field(default_factory=list)

    def as_dict(self) -> dict[str, object]:
        return {
            "local": self.local, "remote": self.remote, "failed": self.failed, "cached": self.cached,
            "failovers": self.failovers, "hedged": self.hedged, "pushed": self.pushed,
        }


class QueryHandler:
    def __init__(
        self,
        config: RobotConfig,
        kb: KnowledgeBase | LiveKB | None,
        client: KBClient,
        wire: str = "compact",
        down: Callable[[str], str | None] = lambda robot_id: None,
        hedge_floor_s: float = 1.0,
        on_failure: Callable[[str, Exception], Awaitable[None]] | None = None,
        pusher: FactPusher | None = None,
    ) -> None:
        if wire not in QUERY_WIRES:
            raise ValueError(f"query wire {wire!r} is not one of {', '.join(QUERY_WIRES)}")
        self.config = config
        self.kb = kb
        self.client = client
        self.wire = wire
        self.stats = QueryStats()
        #: Why a teammate is down (None: up), as the team view knows it (failure detection).
        self._down = down
        #: Told of every holder a request to which failed at the transport:
        #: failed queries count towards failure detection like failed probes.
        self._on_failure = on_failure
        self.hedge_floor_s = hedge_floor_s
        #: Holders whose last request failed at the transport: asked last.
        self._suspects: set[str] = set()
        #: The latest queries' round trips (what hedging and the wait for a push go by).
        self._round_trips: collections.deque[float] = collections.deque(maxlen=ROUND_TRIPS_KEPT)
        #: Publishes the answers this robot gives itself, for teammates that
        #: lack the module (compact wire only: the seed's asked every time).
        self.pusher = pusher if wire == "compact" else None
        #: The answers teammates push to this robot (set by the robot once it observes them).
        self.pushed: PushedFacts | None = None

    def begin(self, task: int) -> None:
        """This robot starts gathering the facts of ``task``."""
        if self.pusher is not None:
            self.pusher.begin(task)

    def pushing_holders(self) -> dict[str, tuple[str, Endpoint]]:
        """Module -> the holder (robot id, endpoint) this robot reads it from
        while every holder is up, for each module it lacks: the one whose
        pushed answers it takes.  None under "compute and communicate": only
        the leader gathers facts, and its holders, which gather none, push none."""
        if self.config.central is not None or self.wire != "compact" or self.config.strategy != "compute-by-all":
            return {}
        held = self.config.team[self.config.robot_id].kbs
        chosen = {}
        for module in sorted({kb for mate in self.config.team.values() for kb in mate.kbs} - set(held)):
            holders = self.config.holders_of(module)
            if self.config.kb_writable:  # the pinned order (_holders_for)
                holders = sorted(holders, key=lambda m: robot_sort_key(m.robot_id))
            if holders:
                chosen[module] = (holders[0].robot_id, holders[0].endpoint)
        return chosen

    def reads_from(self, module: str) -> str | None:
        """The holder the robots of the cluster now put a pinned question
        about ``module`` to (this robot's id if it is that holder); None if
        no holder is live."""
        try:
            chosen = self._holders_for(module, pinned=True)
        except QueryError:
            return None
        return self.config.robot_id if chosen is None else chosen[0].robot_id

    def _holders_for(self, module: str, pinned: bool = False) -> list[Teammate] | None:
        """The remote holders of ``module`` to ask, best first; None if this robot
        answers itself.  Holders known to be down (team view) or that failed
        lately go last: asked only when the others fail too.  ``pinned``: a
        question every robot of the cluster must put to one holder (the
        first live one in robot-id order, this robot included)."""
        if self.config.central is not None:
            return [Teammate("central server", self.config.central, (module,))]
        holders = self.config.holders_of(module)
        if not holders:
            raise QueryError(f"no teammate holds the {module} KB")
        if pinned:
            # One holder, neither hedged nor failed over: another holder may
            # have a write this one has not, and the robots of a cluster must
            # read alike.  If it fails, the robot takes a teammate's decision
            # (Controller._settle).
            holders = sorted(holders, key=lambda m: robot_sort_key(m.robot_id))
            live = [m for m in holders if m.robot_id == self.config.robot_id or self._alive(m.robot_id)]
            if not live:
                raise ModuleUnavailable(module, {m.robot_id: self._why_down(m.robot_id) for m in holders})
            if live[0].robot_id == self.config.robot_id and self.kb is not None:
                return None
            return live[:1]
        if holders[0].robot_id == self.config.robot_id and self.kb is not None:
            return None
        remote = [m for m in holders if m.robot_id != self.config.robot_id]
        if not any(self._alive(m.robot_id) for m in remote):
            raise ModuleUnavailable(module, {m.robot_id: self._why_down(m.robot_id) for m in remote})
        # sorted() is stable: the configured order stays among equals.
        return sorted(remote, key=lambda m: (not self._alive(m.robot_id), m.robot_id in self._suspects))

    def _alive(self, robot_id: str) -> bool:
        return self._down(robot_id) is None

    def _why_down(self, robot_id: str) -> str:
        why = self._down(robot_id)
        return "down" if why is None else f"down ({why})"

    def hedge_after_s(self) -> float:
        """How long to wait for one holder before also asking the next replica:
        a multiple of the recent remote latencies, never under the floor."""
        recent = sorted(self._round_trips)
        if not recent:
            return self.hedge_floor_s
        p90 = recent[min(len(recent) - 1, int(0.9 * len(recent)))]
        return max(self.hedge_floor_s, 4 * p90)

    async def run(self, name: str, params: Mapping[str, str], *, at: int | None = None) -> QueryResult:
        """Run the named query ``name`` wherever its KB module lives.

        ``at``: the task this answer decides.  On a writable team every
        robot then asks one holder, which answers each question of a task
        alike (:meth:`coapkb.kb.live.LiveKB.query_at`)."""
        query = NAMED_QUERIES[name]
        pinned = at is not None and self.config.kb_writable
        holders = self._holders_for(query.kb, pinned)
        asked = {**params, "at": str(at)} if pinned else params
        if holders is None:
            self.stats.local += 1
            assert self.kb is not None
            try:
                text = query.render(params)
                if at is not None and pinned and isinstance(self.kb, LiveKB):
                    result = self.kb.query_at(at, text)
                else:
                    result = self.kb.query(text)
            except KBError as exc:
                self.stats.failed += 1
                raise QueryError(f"{name} on own {query.kb} KB: {exc}") from None
            if self.pusher is not None:
                await self.pusher.offer(query.kb, name, asked)
            return result
        started, before = clock.monotonic(), (self.stats.remote, self.stats.pushed)
        await self._await_push(name, asked, holders[0])
        waited = clock.monotonic() - started
        result = await self._remote(name, asked, holders)
        if (self.stats.remote, self.stats.pushed) != before:  # it crossed the network: asked, or pushed
            latencies = self.stats.remote_latencies
            latencies.append(took := clock.monotonic() - started)
            if len(latencies) > LATENCIES_KEPT:
                del latencies[: len(latencies) - LATENCIES_KEPT]
            if took > SLOW_FACT_S:
                how = "pushed" if self.stats.pushed != before[1] else f"asked after {waited:.2f} s waiting for a push"
                log.info("slow fact: %s for task %s from %s took %.2f s, %s", name, at, holders[0].robot_id, took, how)
        return result

    async def _await_push(self, name: str, params: Mapping[str, str], holder: Teammate) -> None:
        """Give ``holder`` about two round trips to push its answer before
        asking it; not a holder known down or whose last request failed."""
        pushed, endpoint, request = self.pushed, holder.endpoint, named_request(name, params)
        if (pushed is None or not pushed.expects(endpoint) or not self._alive(holder.robot_id)
                or holder.robot_id in self._suspects or self.client.fresh(endpoint, request)):
            return
        answer = await pushed.wait(endpoint, name, params, self.push_wait_s(name))
        if answer is not None and self.client.prime(endpoint, request, answer.max_age, answer.result):
            self.stats.pushed += 1

    def push_wait_s(self, name: str) -> float:
        """How long to wait for a pushed answer to ``name`` before asking:
        as long as its answers usually take to come (PushedFacts.expected_within:
        a lost one then costs little more than the query it replaces), or,
        before that is known, two round trips (the median of the recent
        queries', else the observations' registration; a holder that needs
        another's fact first, the grip, pushes a round trip later); never
        more than two round trips nor the hedging floor."""
        recent = sorted(self._round_trips)
        round_trip = recent[len(recent) // 2] if recent else self.pushed.round_trip_s if self.pushed else None
        ceiling = self.hedge_floor_s if round_trip is None else min(self.hedge_floor_s, 2 * round_trip)
        usual = self.pushed.expected_within(name) if self.pushed else None
        if usual is None:
            return min(PUSH_WAIT_S, max(PUSH_WAIT_FLOOR_S, ceiling))
        return min(ceiling, max(PUSH_WAIT_FLOOR_S, usual))

    async def _remote(self, name: str, params: Mapping[str, str], holders: list[Teammate]) -> QueryResult:
        """Ask the first holder; on a transport failure (dead or unreachable
        peer) ask the next, and when the first is slow, hedge: ask the next
        too and take whichever answers first."""
        query = NAMED_QUERIES[name]
        waiting = list(holders)
        pending: dict[asyncio.Task[QueryResult], Teammate] = {}
        errors: dict[str, str] = {}

        def ask_next() -> None:
            mate = waiting.pop(0)
            pending[asyncio.create_task(self._ask(mate, name, params))] = mate

        ask_next()
        try:
            while pending:
                done, _ = await asyncio.wait(
                    pending, timeout=self.hedge_after_s() if waiting else None, return_when=asyncio.FIRST_COMPLETED
                )
                if not done:  # the holders asked are slow: a replica too
                    self.stats.hedged += 1
                    ask_next()
                    continue
                # In the order they were asked: ``done`` is a set, ordered by id().
                for task in [t for t in pending if t in done]:
                    mate = pending.pop(task)
                    exc = task.exception()
                    if exc is None:
                        self._suspects.discard(mate.robot_id)
                        return task.result()
                    if isinstance(exc, QueryFailed):  # the KB answered: another replica would say the same
                        self.stats.failed += 1
                        raise QueryError(
                            f"{name} to {mate.robot_id} ({mate.endpoint}) for the {query.kb} KB failed: {exc}"
                        ) from None
                    assert isinstance(exc, TransportError), exc
                    self._suspects.add(mate.robot_id)
                    errors[mate.robot_id] = f"{name} to {mate.endpoint} failed: {exc}"
                    if self._on_failure is not None:
                        await self._on_failure(mate.robot_id, exc)
                    if waiting and not pending:
                        self.stats.failovers += 1
                        ask_next()
        finally:
            await cancel_and_wait(pending)
        self.stats.failed += 1
        raise ModuleUnavailable(query.kb, errors)

    async def _ask(self, mate: Teammate, name: str, params: Mapping[str, str]) -> QueryResult:
        """One remote query to one holder; raises QueryFailed or TransportError."""
        query = NAMED_QUERIES[name]
        peer = mate.endpoint
        started = clock.monotonic()
        if self.wire == "compact":
            hits_before = self.client.cache_stats.hits
            result = await self.client.named(peer, name, params, timeout=self.config.query_timeout_s)
            if self.client.cache_stats.hits > hits_before:  # answered from the cache, no traffic
                self.stats.cached += 1
                return result
        else:
            result = await self.client.sparql(
                peer,
                query.render({k: v for k, v in params.items() if k != "at"}),
                accept=ContentFormat.JSON,
                method=Method.POST,
                timeout=self.config.query_timeout_s,
            )
        self.stats.remote += 1
        self._round_trips.append(clock.monotonic() - started)
        return result
