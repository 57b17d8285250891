"""Task Executor (the seed's Fig. 2): carries out the picks assigned to this robot.

Motion is simulated (the seed left path planning and localisation out of
scope too): the robot drives its planned route at the configured speed,
picks, and unloads at the depot when the plan says so; when the plan
charges first, it drives to the dock and charges before all that.  Time runs
``time_scale`` times faster than the wall clock.  Progress is published
through the live part of ``/robot/state``.

At the shelf the robot looks (the world, :mod:`coapkb.world.truth`): an
object that is not there ends its task as not found, and the reason is
published (``missed``) for the feeder's record.  What the robot did is
written into the team's knowledge (:mod:`.knowledge_writer`): the pick, the
delivery, or that the object is missing.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable
from dataclasses import replace
from typing import Any, Protocol

from ..config import ExecutionModel
from ..errors import CoapkbError
from ..world.truth import KBWorld, World
from .job import Job
from .knowledge_writer import DRAIN_WAIT_S, KnowledgeWriter
from .robot_state import LiveState
from .stats import Recharge
from .task_assigner import ChargeStop

log = logging.getLogger(__name__)

#: The log line of a pick, once it counts: the history a checker reads
#: (the simulator's invariant that no task is executed twice).
PICKED = "done: %s (task %d)"
#: The log line of an object not found at the shelf.
NOT_FOUND = "not found: %s (task %d): %s"
#: Not-found tasks the live state names (the latest): the feeder reads them
#: after every decision, and a robot finds few objects missing.
MISSED_KEPT = 8


class LeaseHold(Protocol):
    """None once this robot holds its lease for ``for_s`` seconds, for a
    job of ``task`` (0: none named), else why it is fenced (:meth:`.Lease.hold`)."""

    def __call__(self, for_s: float, task: int = 0) -> Awaitable[str | None]: ...


class TaskExecutor:
    def __init__(
        self,
        model: ExecutionModel,
        start: LiveState,
        publish: Callable[[LiveState], None],
        sleep: Callable[[float], Awaitable[None]] = asyncio.sleep,
        lease: LeaseHold | None = None,
        *,
        robot_id: str = "",
        world: World | None = None,
        knowledge: KnowledgeWriter | None = None,
    ) -> None:
        self.model = model
        self.robot_id = robot_id
        #: What the robot finds at the shelf; without a simulated world, what the KB says.
        self._world: World = world or KBWorld()
        #: Writes the picks, deliveries and missing objects; None: nothing is written.
        self._knowledge = knowledge
        #: Jobs picked and still carried (delivered at the next unload).
        self._carried: list[Job] = []
        #: ``lease(seconds, task)``: None once this robot holds its lease for
        #: that long, for a job of ``task``, else why it is fenced
        #: (coapkb.agent.lease); None = no fence.
        self._lease = lease
        #: Waits out simulated time (wall-clock seconds); a test passes a fast clock.
        self._sleep = sleep
        self.live = start
        self._publish = publish
        self._jobs: asyncio.Queue[Job] = asyncio.Queue()
        self._idle = asyncio.Event()
        self._idle.set()
        self._task: asyncio.Task[None] | None = None
        #: The charges made so far, in order (for the robot's statistics).
        self.recharges: list[Recharge] = []
        #: Jobs of tasks before this one are not this robot's (:meth:`void_before`), and why.
        self._void_before = 0
        self._void_reason = ""

    def start(self) -> None:
        self._task = asyncio.create_task(self._run(), name="task-executor")

    async def aclose(self) -> None:
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass

    def submit(self, job: Job) -> None:
        self._idle.clear()
        self._jobs.put_nowait(job)
        self._update(queued=self._jobs.qsize())

    async def wait_idle(self) -> None:
        await self._idle.wait()

    def _update(self, **changes: Any) -> None:
        self.live = replace(self.live, **changes)
        self._publish(self.live)

    async def _simulate(self, seconds: float) -> None:
        # Simulated physical time: nothing to await but the clock itself.
        await self._sleep(seconds / self.model.time_scale)

    def _forfeit(self, job: Job, why: str) -> None:
        """Drop ``job`` and every queued one without executing them; the
        live state names them, so the feeder sends them round again."""
        dropped = [job.seq]
        while not self._jobs.empty():
            dropped.append(self._jobs.get_nowait().seq)
        log.warning("fenced: dropping tasks %s unexecuted: %s", ", ".join(map(str, dropped)), why)
        self._update(activity="idle", executing=None, queued=0, fenced=self.live.fenced + tuple(dropped),
                     fence_reason=why)
        self._idle.set()

    def void_before(self, seq: int, why: str) -> None:
        """Jobs of tasks before ``seq`` are not this robot's any more: it
        joins its team again at ``seq``, and those tasks went round again
        (or will).  Queued ones are dropped now; one under way, or one
        decided later (a task this robot was still deciding), at its lease
        check, even if a lease is granted: the teammates count this robot
        again, and decided those tasks with it a member (simulator, seed
        30143 of nine robots with partitions: a robot frozen while it
        decided, taken back, then decided its old task and picked it after
        it had gone round again)."""
        self._void_before = max(self._void_before, seq)
        self._void_reason = why
        kept: list[Job] = []
        dropped: list[Job] = []
        while not self._jobs.empty():
            job = self._jobs.get_nowait()
            (dropped if job.seq < seq else kept).append(job)
        for job in kept:
            self._jobs.put_nowait(job)
        if dropped:
            self._drop([job.seq for job in dropped], why)

    def _drop(self, seqs: list[int], why: str) -> None:
        log.warning("dropping tasks %s unexecuted: %s", ", ".join(map(str, seqs)), why)
        self._update(queued=self._jobs.qsize(), fenced=self.live.fenced + tuple(seqs), fence_reason=why)

    async def fenced(self) -> str | None:
        """Why no majority of the cluster grants this robot a lease now, or
        None if one does (or there is no fence)."""
        return None if self._lease is None else await self._lease(0.0)

    async def _leased(self, job: Job, for_s: float) -> bool:
        """True while this robot holds its lease for ``for_s`` more seconds;
        else ``job`` and the queued ones are dropped (:meth:`_forfeit`)."""
        if job.seq < self._void_before:
            self._drop([job.seq], self._void_reason)
            if self._jobs.empty():
                self._update(activity="idle", executing=None)
                self._idle.set()
            return False
        if self._lease is None:
            return True
        why = await self._lease(for_s, job.seq)
        if why is not None:
            self._forfeit(job, why)
        return why is None

    async def _charge(self, job: Job, stop: ChargeStop) -> None:
        await self._simulate(stop.to_dock_m / self.model.speed_m_s)
        self._update(activity="charging", aisle=float(stop.dock.aisle), rack=float(stop.dock.rack))
        await self._simulate(stop.charge_s)
        self.recharges.append(Recharge(job.seq, (stop.dock.aisle, stop.dock.rack), stop.arrive_wh, stop.full_wh))
        log.info("charged at (%d, %d): %.1f -> %.1f Wh (task %d)", stop.dock.aisle, stop.dock.rack,
                 stop.arrive_wh, stop.full_wh, job.seq)
        self._update(activity="travelling")

    async def _look(self, job: Job) -> str | None:
        """None if ``job``'s object is on the shelf (now in the robot's
        hands), else why not.  A world that does not answer is no reason to
        leave the object: the robot trusts the KB, and says so."""
        try:
            return await self._world.take(job.object, self.robot_id, job.seq)
        except CoapkbError as exc:
            log.warning("task %d: %s; taking %s as the KB says", job.seq, exc, job.object)
            return None

    async def _run(self) -> None:
        while True:
            job = await self._jobs.get()
            self._update(activity="travelling", executing=job.object, queued=self._jobs.qsize())
            if job.charge is not None:
                await self._charge(job, job.charge)
            await self._simulate(job.to_object_m / self.model.speed_m_s)
            # The pick is what must never happen twice: it starts only under a
            # lease that outlasts it, and counts only if the lease still holds
            # when it is over (this robot may have been frozen meanwhile, and
            # the others may have re-assigned the job: then it is put back).
            if not await self._leased(job, self.model.pick_s / self.model.time_scale):
                continue
            self._update(activity="picking", aisle=float(job.aisle), rack=float(job.rack))
            await self._simulate(self.model.pick_s)
            if not await self._leased(job, 0.0):
                continue
            # Only under the lease does the robot take the object off the
            # shelf: a fenced robot leaves it for the one doing the task again.
            why = await self._look(job)
            if why is not None:
                # Done too: the robot went there; the task ends as not found.
                log.warning(NOT_FOUND, job.object, job.seq, why)
                self._update(done=self.live.done + 1, missed=(self.live.missed + ((job.seq, why),))[-MISSED_KEPT:])
                if self._knowledge is not None:
                    self._knowledge.missing(job)
            else:
                # Done once picked: the count the feeder reads says what nobody may pick again.
                self._update(done=self.live.done + 1)
                log.info(PICKED, job.object, job.seq)
                self._carried.append(job)
                if self._knowledge is not None:
                    self._knowledge.picked(job)
            if job.to_depot_m > 0:
                self._update(activity="unloading")
                await self._simulate(job.to_depot_m / self.model.speed_m_s)
                self._update(aisle=float(job.depot[0]), rack=float(job.depot[1]))
                if self._knowledge is not None and self._carried:
                    self._knowledge.delivered(self._carried, job.depot)
                self._carried = []
            if self._knowledge is not None and why is None and job.load_after_kg is not None:
                self._knowledge.load(job.load_after_kg, job.battery_after_wh or 0.0)
            if self._jobs.empty() and self._knowledge is not None:
                # Idle from now: what it wrote lazily goes out before it says so.
                self._knowledge.flush()
                flushed = asyncio.get_running_loop().time()
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(DRAIN_WAIT_S):
                        await self._knowledge.drained()
                log.info("idle: its facts went out in %.3f s", asyncio.get_running_loop().time() - flushed)
            idle = self._jobs.empty()
            self._update(activity="idle" if idle else "travelling", executing=None)
            if idle:
                self._idle.set()
