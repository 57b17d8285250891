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

from .. import clock
from ..agent.observed_states import ObservedStates
from ..agent.stats import RobotStats
from ..host import Network
from ..transport import ClientSecurity
from ..transport.base import TrafficCounters
from . import readiness, robot_stats
from .channel import Channel, FeederSettings
from .membership import Membership
from .orphans import idle
from .record import TaskRecord, claim_of, mark_not_found, unclaim
from .roster import Roster
from .task_poster import TaskPoster
from .tasks import Entry, FeederError, Restock, split_tasks

if TYPE_CHECKING:
    from .restock import Restocker

log = logging.getLogger(__name__)

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


class Feeder:
    """The team's task source.  Open with :meth:`open` (an async context
    manager), then :meth:`feed`."""

    def __init__(self, channel: Channel) -> None:
        self.channel = channel
        self.membership = Membership(channel)
        self.poster = TaskPoster(channel, self.membership)
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
        """Ask every robot once for its state before feeding
        (:func:`.readiness.check_ready`): this feeder's tasks follow on
        from those the robots took.  ``hints``: robot -> what to do about
        one that does not answer, added to the error."""
        self._first_seq = await readiness.check_ready(self.channel, self.membership, timeout, hints)

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
        return await robot_stats.collect_stats(self.channel, robots, maybe)

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
                joining, left_behind = await membership.ready_for(cluster, seq, records)
                reruns += left_behind
                record = await self.poster.feed_task(index, cluster, seq, name, joining, reassigned_from,
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
                                        *membership.undecided(cluster, records),
                                        *membership.left_by_restarts(cluster, records)]}
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
