"""One run of a started team: its task list fed by the feeder in this
process (:mod:`coapkb.feeder`), its scheduled faults carried out
(:mod:`.fault_injector`), the robots' statistics sampled while it lasts
and collected once every robot is done, and its record (:mod:`.record`).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

from ..agent.observed_states import STATE_PATH
from ..agent.robot_state import RobotState
from ..agent.stats import RobotStats
from ..cancelling import cancel_and_wait
from ..feeder import Feeder, FeederSettings, FeedOutcome, Roster, TaskRecord
from ..feeder.restock import Restocker
from ..feeder.tasks import Entry
from ..transport.base import TrafficCounters, TransportError
from .fault_injector import FaultInjector
from .processes import TeamProcesses
from .record import FaultEvent, TeamRecord
from .team_spec import TeamSpec

if TYPE_CHECKING:
    from ..transport import ClientSecurity


class TeamRun:
    """Feeds one task list to the team ``processes`` run, as ``roster`` lists
    it for the feeder, with ``settings`` and ``security``; ``restocker``
    makes the list's deliveries (None: the list has none)."""

    def __init__(
        self, spec: TeamSpec, processes: TeamProcesses, roster: Roster, settings: FeederSettings,
        security: ClientSecurity | None, restocker: Restocker | None = None,
    ) -> None:
        self.spec = spec
        self.processes = processes
        self.roster = roster
        self.settings = settings
        self.security = security
        self.restocker = restocker

    async def feed(
        self,
        tasks: Sequence[Entry],
        progress: Callable[[TaskRecord], None] | None = None,
        finished: Callable[[], Awaitable[None]] | None = None,
        on_state: Callable[[str, RobotState], None] | None = None,
        on_stats: tuple[float, Callable[[dict[str, RobotStats]], None]] | None = None,
    ) -> TeamRecord:
        """Feed the tasks, wait for every robot to finish executing, return the
        record (the arguments are :meth:`coapkb.harness.team.Team.run`'s)."""

        def on_progress(record: TaskRecord) -> Awaitable[None] | None:
            if progress is not None:
                progress(record)
            # A fault scheduled at this task: carried out before the cluster's next task is fed.
            return faults.after(record)

        restocker = self.restocker
        # Told of states (a recording): each robot's whole state, where it is included.
        settings = self.settings if on_state is None else replace(self.settings, watch=STATE_PATH)
        async with contextlib.AsyncExitStack() as closing, Feeder.open(self.roster, settings, self.security) as feeder:
            if restocker is not None:
                closing.push_async_callback(restocker.client.aclose)
                feeder.restocker = restocker
            if on_state is not None:
                feeder.watcher.listeners.append(on_state)
            started = time.monotonic()
            faults = FaultInjector(self.spec.faults, self.spec.clusters(), self.processes, feeder, started)
            injector = asyncio.create_task(faults.by_time(), name="faults")
            sampler = None if on_stats is None else asyncio.create_task(_sample(feeder, *on_stats), name="stats")
            try:
                outcome = await feeder.feed(tasks, on_progress, started)
                if finished is not None:
                    await finished()
                stats = await self._statistics(feeder, faults)
                traffic = feeder.traffic  # a copy: the client still counts while closing
            finally:
                await cancel_and_wait((injector, sampler))
            down, down_at = dict(feeder.watcher.down), dict(feeder.watcher.down_at)
        faults.note_detection(down_at)
        return team_record(self.spec, outcome, stats, traffic, faults.events, down)

    async def _statistics(self, feeder: Feeder, faults: FaultInjector) -> dict[str, RobotStats]:
        """Every robot's statistics once all is done: the live ones', and those
        of the robots the team has down that answer all the same."""
        watcher = feeder.watcher
        # A resumed robot is down for the team but answers: its counts
        # show what it executed (nothing the others were given).
        resumed = [r for r in self.spec.robot_ids if r in self.processes.resumed and r in watcher.down]
        # A fault under way (a restart whose process is starting) ends first; a robot
        # whose process is dead is asked only if it answers: its death may not be seen yet.
        async with faults.busy:
            dead = [r for r in watcher.alive if self.processes.dead(r)]
            # A kill the run ended too soon to notice (its tasks went on
            # without the robot, and the feeder asked it nothing): asked now,
            # so the record says when the team found it down, not nothing.
            await asyncio.gather(*(watcher.probe(r, reobserve=False) for r in dead))
            return await feeder.collect_stats([r for r in watcher.alive if r not in dead], [*resumed, *dead])


async def _sample(feeder: Feeder, every_s: float, sink: Callable[[dict[str, RobotStats]], None]) -> None:
    """Every ``every_s`` seconds, every live robot's statistics to ``sink``;
    a robot that does not answer is left out of that sample."""
    while True:
        await asyncio.sleep(every_s)  # a sampling period: nothing to await but the clock
        watcher = feeder.watcher
        try:
            stats = await feeder.collect_stats([], maybe=[r for r in watcher.alive])
        except TransportError:
            continue
        sink(stats)


def team_record(
    spec: TeamSpec,
    outcome: FeedOutcome,
    stats: dict[str, RobotStats],
    feeder: TrafficCounters,
    faults: list[FaultEvent],
    down: dict[str, str],
) -> TeamRecord:
    """The record of one run of ``spec``'s team (real processes or simulated)."""
    return TeamRecord(
        mode=spec.mode,
        transport=spec.transport,
        strategy=spec.strategy,
        query_wire=spec.query_wire,
        robots=spec.robot_ids,
        clusters=spec.clusters(),
        tasks=outcome.tasks,
        # Rounded as the JSON record has always been, so the benchmark row
        # made from this record holds the same numbers as before.
        coordination_s=round(outcome.coordination_s, 6),
        completion_s=round(outcome.completion_s, 6),
        robot_stats=stats,
        feeder_traffic=feeder,
        faults=faults,
        down=down,
    )
