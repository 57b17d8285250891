"""The feeding loop: the task list split into contiguous shares, one per
cluster, fed in parallel; within a cluster tasks go out one at a time (the
seed's "sequentially triggered from an external source"): the next once
every robot of the cluster has decided the previous one."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import cbor2

from .. import clock
from ..agent.observed_states import ObservedStates, States
from ..agent.robot_state import RobotState
from ..agent.stats import RobotStats
from ..host import Network
from ..transport import ClientSecurity
from ..transport.base import TrafficCounters, TransportError
from ..transport.messages import ContentFormat, Method, Request
from .channel import Channel, FeederSettings
from .membership import Membership, PendingTask
from .orphans import idle
from .record import TaskRecord, claim_of, mark_not_found, unclaim
from .roster import Roster
from .tasks import Entry, FeederError, Restock, split_tasks, task_post

if TYPE_CHECKING:
    from .restock import Restocker

log = logging.getLogger(__name__)

STATS_PATH = "/robot/stats"
#: Requests for one robot's statistics before the feeder gives up on them.
STATS_TRIES = 3


#: Told of each task once decided; what it returns (if anything) is awaited
#: before the cluster's next task (a fault scheduled at that task).
Progress = Callable[[TaskRecord], Awaitable[None] | None]


@dataclass(frozen=True)
class FeedOutcome:
    """What feeding a task list gave: a record per task (re-runs included),
    in the order given, and how long it took."""

    tasks: list[TaskRecord]
    #: Feeding the first task until every cluster decided its last one, seconds.
    coordination_s: float
    #: Until every robot also finished executing, seconds.
    completion_s: float


def _last_task(state: RobotState) -> int:
    """The number of the last task ``state``'s robot took and decided (0: none)."""
    return max(state.plan.seq, state.last.seq if state.last is not None else 0)


class Feeder:
    """The team's task source.  Open with :meth:`open` (an async context
    manager), then :meth:`feed`."""

    def __init__(self, channel: Channel) -> None:
        self.channel = channel
        self.membership = Membership(channel)
        #: Cluster index -> its first task's number (1, unless robots took an earlier feeder's tasks).
        self._first_seq: dict[int, int] = {}
        #: Makes the task list's deliveries (``restock OBJECT``); None: a list with one is refused.
        self.restocker: Restocker | None = None
        #: Objects this feed assigned: a delivery of one waits for its pick.
        self._assigned_objects: set[str] = set()

    @classmethod
    @contextlib.asynccontextmanager
    async def open(cls, roster: Roster, settings: FeederSettings, security: ClientSecurity | None = None,
                   network: Network | None = None) -> AsyncIterator[Feeder]:
        async with Channel.open(roster, settings, security, network) as channel:
            yield cls(channel)

    @property
    def watcher(self) -> ObservedStates:
        """Every robot's observed state, and those the feeder has down."""
        return self.channel.watcher

    @property
    def traffic(self) -> TrafficCounters:
        """A copy of the feeder's own transport counters."""
        return replace(self.channel.client.counters)

    async def check_ready(self, timeout: float, hints: Mapping[str, str] | None = None) -> None:
        """Ask every robot once for its state before feeding: each must
        answer, be done with earlier tasks (another feeder's), and have taken
        the same tasks as the rest of its cluster; this feeder's tasks follow
        on from theirs.  ``hints``: robot -> what to do about one that does
        not answer, added to the error."""
        channel = self.channel

        async def ask(robot_id: str) -> RobotState | str:
            """``robot_id``'s state, or why it cannot be fed."""
            endpoint = channel.endpoint(robot_id)
            try:
                response = await channel.client.request(endpoint, channel.settings.watch_request, timeout=timeout)
            except TransportError as exc:
                hint = f"; {hints[robot_id]}" if hints and robot_id in hints else ""
                return f"{robot_id} does not answer at {endpoint} ({exc}){hint}"
            try:
                state = RobotState.decode(response.payload) if response.status.is_success else None
            except ValueError:
                state = None
            if state is None:
                return f"{robot_id} at {endpoint} answered {response.status.dotted}, not its state"
            if state.live.activity != "idle" or state.live.queued:
                return f"{robot_id} is still executing earlier tasks: feed it once it is idle"
            return state

        # Every robot asked to the end: one line names them all, and no request is left behind.
        robots = channel.roster.robot_ids
        answers = await asyncio.gather(*(ask(r) for r in robots))
        problems = [a for a in answers if isinstance(a, str)]
        if problems:
            raise FeederError("; ".join(problems))
        states = {r: a for r, a in zip(robots, answers) if isinstance(a, RobotState)}
        for index, cluster in enumerate(channel.roster.clusters):
            taken = {r: _last_task(states[r]) for r in cluster}
            # A robot started again by hand: a new process that has taken no
            # task while its teammates took some.  It joins them at this
            # feeder's first task, as a robot restarted during a run does
            # (its teammates tell the new process by its boot and admit it
            # there).  Robots at different tasks otherwise are refused.
            fresh = [r for r, n in taken.items() if n == 0 and not states[r].live.done]
            went_on = {n for r, n in taken.items() if r not in fresh}
            if fresh and len(went_on) == 1 and went_on != {0}:
                for robot_id in fresh:
                    log.warning("%s started again by hand: it joins its teammates at task %d",
                                robot_id, max(went_on) + 1)
                    await self.membership.rejoin(robot_id)
            elif len(set(taken.values())) > 1:
                raise FeederError(f"the robots of cluster {index + 1} have taken different tasks "
                                  f"({', '.join(f'{r}: up to {n}' for r, n in taken.items())}): restart them")
            self._first_seq[index] = max(taken.values(), default=0) + 1
        for robot_id, state in states.items():
            self.membership.set_done_before(robot_id, state.live.done)

    async def feed(
        self,
        tasks: Sequence[Entry],
        progress: Progress | None = None,
        started: float | None = None,
    ) -> FeedOutcome:
        """Feed ``tasks`` (deliveries among them: :mod:`.restock`) and wait until every robot has executed what it took;
        ``progress`` is called with each task's record once it is decided
        (if it returns an awaitable, the cluster's next task waits for it).
        ``started``: the run's start (monotonic), if not now."""
        started = clock.monotonic() if started is None else started
        clusters = self.channel.roster.clusters
        if self.restocker is None and any(isinstance(t, Restock) for t in tasks):
            raise FeederError("the task list restocks objects, but this feeder cannot deliver them")
        shares = split_tasks(tasks, len(clusters))
        per_cluster = await asyncio.gather(
            *(self._feed_cluster(index, list(cluster), share, progress)
              for index, (cluster, share) in enumerate(zip(clusters, shares)))
        )
        coordination_s = max(decided_at for _, decided_at in per_cluster) - started
        completion_s = clock.monotonic() - started
        records = [record for share_records, _ in per_cluster for record in share_records]
        # Restore the order given: cluster shares are contiguous.
        records.sort(key=lambda r: (r.cluster, r.seq))
        return FeedOutcome(records, coordination_s, completion_s)

    async def collect_stats(self, robots: Sequence[str], maybe: Sequence[str] = ()) -> dict[str, RobotStats]:
        """Every robot's statistics; those of ``maybe`` if they answer."""
        stats = {}
        for robot_id in [*robots, *maybe]:
            try:
                stats[robot_id] = await self._stats_of(robot_id)
            except TransportError:
                if robot_id in maybe:
                    continue
                raise
        return stats

    async def _stats_of(self, robot_id: str) -> RobotStats:
        """``robot_id``'s statistics, asked up to :data:`STATS_TRIES` times: a
        burst of loss on a radio link can swallow every retransmission of one
        download, and a run's record is worth another try (found in the
        simulator)."""
        channel = self.channel
        request = Request(Method.GET, STATS_PATH, accept=ContentFormat.CBOR)
        for attempt in range(1, STATS_TRIES + 1):
            try:
                response = await channel.client.request(
                    channel.endpoint(robot_id), request, timeout=channel.settings.query_timeout_s
                )
            except TransportError:
                if attempt == STATS_TRIES:
                    raise
                continue
            return RobotStats.from_dict(cbor2.loads(response.payload))
        raise AssertionError("unreachable")

    async def _feed_cluster(
        self, index: int, cluster: list[str], share: list[Entry], progress: Progress | None
    ) -> tuple[list[TaskRecord], float]:
        """Feed one cluster's share; returns its records and when its last task was decided."""
        membership, watcher = self.membership, self.channel.watcher
        records: list[TaskRecord] = []
        #: (robot, task) -> record, for the tasks a robot reports not found.
        assigned: dict[tuple[str, int], TaskRecord] = {}
        #: (robot, task) -> the later skips that name its pick: named again
        #: if that task's robot does not find the object.
        claims: dict[tuple[str, int], list[TaskRecord]] = {}

        def not_found() -> None:
            for found in mark_not_found(assigned, watcher.states):
                for skip in claims.pop((found.assigned_to or "", found.seq), ()):
                    unclaim(skip, found)
        queue: list[tuple[Entry, int | None]] = [(name, None) for name in share]
        #: Objects delivered back since the cluster last decided them: their next task says so.
        restocked: set[str] = set()
        #: Tasks of a robot's previous process, found when it joins again.
        reruns: list[TaskRecord] = []
        seq = self._first_seq.get(index, 1) - 1
        decided_at = clock.monotonic()
        while queue:
            for name, reassigned_from in queue:
                if isinstance(name, Restock):
                    assert self.restocker is not None  # checked by feed()
                    await self.restocker.restock(
                        name.object, index, name.object in self._assigned_objects, watcher.down,
                        lambda: sum(watcher.states[r].live.done for r in cluster if r in watcher.states))
                    restocked.add(name.object)
                    continue
                seq += 1
                joining = membership.joining(cluster)
                if joining:
                    reruns += membership.prepare_join(records, joining, seq)
                if records:
                    await membership.take_back(cluster, records)
                record = await self._feed_task(index, cluster, seq, name, joining, reassigned_from,
                                               name in restocked, records)
                restocked.discard(name)
                record.reassigned_from = reassigned_from
                records.append(record)
                if record.assigned_to is not None:
                    assigned[(record.assigned_to, record.seq)] = record
                    self._assigned_objects.add(name)
                claim = claim_of(record)
                if claim is not None and claim in assigned:
                    if assigned[claim].not_found is not None:
                        unclaim(record, assigned[claim])
                    else:
                        claims.setdefault(claim, []).append(record)
                not_found()
                if progress is not None:
                    held = progress(record)
                    if held is not None:
                        await held
            decided_at = clock.monotonic()
            await self._until_executed(index, cluster)
            # Tasks assigned to robots that went down before executing them
            # go round again, in their order, to the survivors: once the
            # down robot can no longer pick them (the fence).
            await membership.recover(cluster, records)
            # After the recovery, which reads a down robot's final state: one
            # still granted (settled) reports there what it did not find.
            not_found()
            found = {r.seq: r for r in [*reruns, *membership.orphans(records),
                                        *membership.undecided(cluster, records)]}
            reruns = []
            queue = [(found[s].object, s) for s in sorted(found)]
        return records, decided_at

    async def _until_executed(self, index: int, cluster: list[str]) -> None:
        """Until the cluster's survivors have executed everything: a robot
        that dies meanwhile is found by the stalled wait's liveness
        requests.  A long shift's robots decide far ahead of their wheels
        (3,000 tasks leave hours of jobs queued), so the wait lasts while
        they finish jobs, and fails once none did for four task timeouts."""
        channel, watcher = self.channel, self.channel.watcher
        what = f"cluster {index + 1} to finish executing"

        def done() -> int:
            return sum(watcher.states[r].live.done for r in cluster if r in watcher.states)

        while True:
            before = done()
            try:
                await channel.wait_for(lambda s: all(r in watcher.down or idle(s, r) for r in cluster),
                                       channel.settings.task_timeout_s * 4, what)
                return
            except FeederError:
                if done() == before:
                    raise
                log.info("%s: %d jobs done meanwhile; waiting on", what, done() - before)

    async def _post_to_joiners(self, request: Request, seq: int, name: str, joining: Sequence[str]) -> list[str]:
        """Post task ``seq`` to the robots joining at it, before their
        teammates; the joiners it reached.  One it did not reach (found down:
        the process that was to join died, and another may have started since)
        is not named to its teammates: they would admit it at this task and
        wait for a plan after the previous one, which no process of it
        publishes, until their wait ran out and they decided nothing (found in
        the simulator: a robot killed again soon after its restart, and
        restarted once more just after the feeder posted its join).  It
        joins at a later task, once the feeder is told of its restart."""
        channel, watcher = self.channel, self.channel.watcher
        await asyncio.gather(*(channel.post_task(r, request, seq, name) for r in joining))
        missed = [r for r in joining if r in watcher.down]
        if missed:
            log.warning("%s did not take task %d, at which %s to join: %s not named to the teammates",
                        ", ".join(missed), seq, "it was" if len(missed) == 1 else "they were",
                        "it is" if len(missed) == 1 else "they are")
        return [r for r in joining if r not in watcher.down]

    async def _feed_task(
        self, index: int, cluster: list[str], seq: int, name: str, joining: Sequence[str] = (),
        again: int | None = None, restocked: bool = False, records: Sequence[TaskRecord] = (),
    ) -> TaskRecord:
        channel, watcher = self.channel, self.channel.watcher
        fed = clock.monotonic()
        request = task_post(seq, name, joining, again, restocked)
        live = [r for r in cluster if r not in watcher.down]
        if not live:
            why = "; ".join(f"{r}: {watcher.down[r]}" for r in cluster)
            others = len(watcher.down) - len(cluster)
            raise FeederError(f"every robot of cluster {index + 1} is down ({why})"
                              + (f"; {others} robots of other clusters too" if others else ""))
        joined = await self._post_to_joiners(request, seq, name, joining)
        if joined != list(joining):
            request = task_post(seq, name, joined, again, restocked)
        await asyncio.gather(*(channel.post_task(r, request, seq, name) for r in live if r not in joining))

        def decided(states: States, robot_id: str) -> bool:
            last = states[robot_id].last if robot_id in states else None
            return last is not None and last.seq >= seq

        def undecided(states: States) -> list[str]:
            return [r for r in cluster if r not in watcher.down and not decided(states, r)]

        deciding = asyncio.ensure_future(channel.wait_for(
            lambda s: not undecided(s),
            channel.settings.task_timeout_s,
            f"decisions on task {seq} ({name}) from {', '.join(r for r in cluster if r not in watcher.down)}",
            pending=undecided, of=len(live),
        ))
        try:
            if records:
                await self.membership.take_back_while(cluster, records, PendingTask(seq, name, request), deciding)
            states = await deciding
        finally:
            deciding.cancel()
        record = TaskRecord(object=name, cluster=index + 1, seq=seq, coordination_s=clock.monotonic() - fed,
                            joined=joined)
        decisions = {r: d for r in cluster if decided(states, r) and (d := states[r].last) is not None}
        if len({(d.assigned_to, d.unavailable, d.error) for d in decisions.values()}) > 1:
            # Robots that differ may have decided and then died before the
            # feeder noticed: ask each once, so the dead ones' decisions are void.
            await asyncio.gather(*(watcher.probe(r) for r in decisions if r not in watcher.down))
        # The decision is the survivors': a robot that decided and then went
        # down executes nothing (its task, if any, goes round again), and one
        # left out of a newer membership by the others took no part in it.
        newest = max(decisions.values(), key=lambda d: d.epoch, default=None)
        survivors = [r for r in decisions if r not in watcher.down]
        for robot_id in cluster:
            decision = decisions.get(robot_id)
            if decision is None:
                record.absent[robot_id] = watcher.down.get(robot_id, "no decision")
                continue
            if robot_id in watcher.down and survivors:
                record.absent[robot_id] = f"{watcher.down[robot_id]} (its decision is void)"
                continue
            if newest is not None and decision.epoch < newest.epoch and robot_id not in newest.members:
                record.absent[robot_id] = f"left out of membership epoch {newest.epoch} (its decision is void)"
                continue
            record.decisions[robot_id] = decision.assigned_to
            record.epochs[robot_id] = decision.epoch
            if not record.members:
                # A robot's outcome names the members only once they changed:
                # at epoch 0 they are the cluster the feeder fed.
                record.members = list(decision.members or (sorted(cluster) if decision.epoch == 0 else ()))
            if decision.error:
                record.errors[robot_id] = decision.error
            if decision.unavailable and record.unavailable is None:
                record.unavailable = decision.unavailable
            if decision.skipped:
                record.skipped = True
                record.skip_reason = record.skip_reason or decision.skip_reason
            if decision.costs and not record.costs:
                record.costs = dict(decision.costs)
                record.reasons = dict(decision.reasons)
        assigned = {d for d in record.decisions.values() if d is not None}
        record.assigned_to = assigned.pop() if len(assigned) == 1 else None
        return record
