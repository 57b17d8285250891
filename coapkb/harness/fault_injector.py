"""A run's scheduled faults carried out on the team's processes: those
scheduled by time at their wall times after the first task was fed, those
scheduled by task once their cluster decided it; each one at a time, told
to the feeder where it must know (a restarted robot rejoins), and kept as a
:class:`~.record.FaultEvent` of the run's record.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Mapping, Sequence

from ..feeder import Feeder, TaskRecord
from .processes import TeamProcesses
from .record import FaultEvent
from .team_spec import Fault

log = logging.getLogger(__name__)


class FaultInjector:
    """The faults of one run, carried out on ``processes`` while ``feeder`` feeds."""

    def __init__(
        self, faults: Sequence[Fault], clusters: Sequence[Sequence[str]], processes: TeamProcesses,
        feeder: Feeder, started: float,
    ) -> None:
        self.processes = processes
        self.feeder = feeder
        #: When the first task was fed (time.monotonic()): faults by time count from it.
        self.started = started
        #: What was carried out, in order.
        self.events: list[FaultEvent] = []
        #: Held while a fault is carried out: the run's end waits for one under way.
        self.busy = asyncio.Lock()
        self._by_time = sorted((f for f in faults if f.at_task is None), key=lambda f: f.at_s)
        self._by_task = sorted((f for f in faults if f.at_task is not None), key=lambda f: f.at_task or 0)
        self._cluster_of = {r: n for n, cluster in enumerate(clusters, 1) for r in cluster}

    async def by_time(self) -> None:
        """Carry out the faults scheduled by time, at their wall times after :attr:`started`."""
        for fault in self._by_time:
            # A schedule, not a wait for an event: the user asked for this time.
            await asyncio.sleep(max(0.0, self.started + fault.at_s - time.monotonic()))
            await self._carry_out(fault)

    def after(self, record: TaskRecord) -> Awaitable[None] | None:
        """The faults due once ``record``'s task is decided, to be carried out
        before its cluster's next task is fed (None when none is due)."""
        due = [f for f in self._by_task
               if self._cluster_of[f.robot] == record.cluster and record.seq >= (f.at_task or 0)]
        for fault in due:
            self._by_task.remove(fault)
        return self._carry_all(due) if due else None

    def note_detection(self, down_at: Mapping[str, float]) -> None:
        """How long after each kill or stop the team found the robot down
        (``down_at``: when the feeder's watcher did, by robot)."""
        for event in self.events:
            if event.robot in down_at and event.action in ("kill", "stop"):
                event.detected_after_s = round(down_at[event.robot] - self.started - event.at_s, 3)

    async def _carry_all(self, faults: list[Fault]) -> None:
        for fault in faults:
            await self._carry_out(fault)

    async def _carry_out(self, fault: Fault) -> None:
        async with self.busy:
            at_s = round(time.monotonic() - self.started, 3)
            if fault.action == "restart":
                await self.processes.restart(fault.robot, "robot")
                await self.feeder.membership.rejoin(fault.robot)  # it joins at the next task fed
                log.warning("restarted %s at %.1fs", fault.robot, at_s)
            elif fault.action in ("stop", "resume"):
                self.processes.pause(fault.robot, fault.action == "stop")
                log.warning("%s %s at %.1fs", "stopped" if fault.action == "stop" else "resumed", fault.robot, at_s)
            else:
                await self.processes.kill(fault.robot)
                log.warning("killed %s at %.1fs", fault.robot, at_s)
            self.events.append(FaultEvent(fault.action, fault.robot, at_s))
