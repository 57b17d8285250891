"""What a robot (or the task feeder) knows of the team's states: pushed by
Observe (RFC 7641) on each robot's state resource, never polled, and which
robots are down, found from the same exchanges.

:class:`ObservedStates` is what its callers use; it joins two parts, each
its own concern: the :class:`~.state_watcher.StateWatcher` (observations,
their refresh, probes, waits and the repair of lost notifications) and the
:class:`~.failure_detector.FailureDetector` (liveness timeouts, suspicion,
indirect probes, down and back).  A down robot is not watched or asked any
more until it is readmitted (:meth:`ObservedStates.readmit`): a restarted
process is a new member, admitted at a task boundary."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Collection, Mapping, Sequence

from ..transport.base import ClientTransport, Endpoint, TransportError
from ..transport.messages import ContentFormat, Method, Request
from ..transport.rtt import RttEstimator
from .failure_detector import (
    FAILURES_TO_DOWN,
    INDIRECT_PROBE_TIMEOUTS,
    INDIRECT_PROBES,
    FailureDetector,
    liveness_floor_s,
    liveness_timeout_s,
)
from .local_health import LoopHealth
from .robot_state import RobotState
from .state_watcher import States, StateWatcher

__all__ = [
    "FAILURES_TO_DOWN", "INDIRECT_PROBES", "INDIRECT_PROBE_TIMEOUTS", "OUTCOME_PATH", "PLAN_PATH", "STATE_PATH",
    "ObservedStates", "States", "indirect_probe", "liveness_floor_s", "liveness_timeout_s",
]

#: Full state: live progress and the last decision (the feeder, people).
STATE_PATH = "/robot/state"
#: Planned state only: all a teammate needs to assign tasks.
PLAN_PATH = "/robot/plan"
#: What the feeder acts on: each decision's outcome and the job queue's
#: standing, notified only when it changes (RobotState.encode_outcome).
OUTCOME_PATH = "/robot/outcome"


async def indirect_probe(transport: ClientTransport, helpers: Sequence[Endpoint], robot_id: str,
                         request_timeout_s: float) -> bool:
    """Whether one of the first :data:`INDIRECT_PROBES` ``helpers`` reaches
    ``robot_id`` now (``GET /robot/plan?probe=ROBOT`` on each, at once): how
    callers answer :attr:`FailureDetector.confirm_silence`."""
    request = Request(Method.GET, PLAN_PATH, {"probe": robot_id}, accept=ContentFormat.CBOR)

    async def via(helper: Endpoint) -> bool:
        try:
            # The helper's own request to the robot takes up to a timeout of its own.
            response = await transport.request(helper, request, timeout=INDIRECT_PROBE_TIMEOUTS * request_timeout_s)
        except TransportError:
            return False
        return response.status.is_success

    # Tasks made here, in the helpers' order: as_completed would wrap bare
    # coroutines from a set, starting them in an order that follows id().
    probes = [asyncio.create_task(via(h)) for h in helpers[:INDIRECT_PROBES]]
    for done in asyncio.as_completed(probes):
        if await done:
            return True
    return False


class ObservedStates:
    """The latest state of each robot in ``endpoints`` (:attr:`watcher`) and
    which of them are down (:attr:`detector`), for the task feeder and a
    robot's team view.  Each member below is its part's, but for the few
    that take both: readmitting and reviving a robot, and how long finding
    one down takes."""

    def __init__(
        self,
        transport: ClientTransport,
        endpoints: Mapping[str, Endpoint],
        path: str,
        *,
        refresh_s: float = 10.0,
        request_timeout_s: float = 10.0,
        liveness: bool = False,
        liveness_floor_s: float = 1.0,
        health: LoopHealth | None = None,
    ) -> None:
        # Notified of every state stored and every robot down or back: what waits wait on.
        changed = asyncio.Condition()
        self.detector = FailureDetector(endpoints, changed, self._stop_watching, liveness=liveness,
                                        liveness_floor_s=liveness_floor_s, health=health)
        self.watcher = StateWatcher(transport, endpoints, path, self.detector, changed,
                                    refresh_s=refresh_s, request_timeout_s=request_timeout_s)

    def _stop_watching(self, robot_id: str) -> None:
        self.watcher.stop_watching(robot_id)

    def readmit(self, robot_id: str, boot: int = 0) -> None:
        """Count on ``robot_id`` again: a new process of it has joined.  What
        was observed of the old one is forgotten, so the new incarnation's
        state is taken as it comes, not as a restart; if ``boot`` names the
        process that joined, another one found there is a restart."""
        self.detector.readmit(robot_id)
        self.watcher.forget(robot_id, boot)

    async def expect_process(self, robot_id: str, boot: int) -> None:
        """Process ``boot`` of ``robot_id`` is the one counted on (it took its
        join): another one observed there is a restart after it."""
        await self.watcher.expect_process(robot_id, boot)

    async def process_gone(self, robot_id: str, reason: str) -> None:
        """The process of ``robot_id`` counted on is gone (the feeder found a
        new one, which joins at a later task): down, and gone."""
        await self.detector.restarted(robot_id, reason)

    async def revive(self, robot_id: str) -> None:
        """Count on ``robot_id`` again: declared down, it answered as the same
        process (the suspicion was false: this process was the one cut off).
        What was observed of it stays, so a new process of it is still told
        apart by its ``boot`` and found down at once (:meth:`StateWatcher.update`)."""
        if await self.detector.revive(robot_id):
            self.watcher.watch(robot_id)

    @property
    def detection_s(self) -> float:
        """How long a stalled wait may take to find a silent robot down: a
        refresh period, then :data:`FAILURES_TO_DOWN` requests' timeouts and
        an indirect probe's, after the grace a readmitted robot still has
        (its failures do not count before: a process that died before it was
        ever reached is found down only then)."""
        return (self.detector.grace_s + self.refresh_s
                + (FAILURES_TO_DOWN + INDIRECT_PROBE_TIMEOUTS) * self.request_timeout_s + 1.0)

    # The watcher's part.

    @property
    def states(self) -> States:
        return self.watcher.states

    @property
    def listeners(self) -> list[Callable[[str, RobotState], None]]:
        return self.watcher.listeners

    @property
    def refreshes(self) -> int:
        return self.watcher.refreshes

    @property
    def repairs(self) -> int:
        return self.watcher.repair.repairs

    @property
    def lateness(self) -> RttEstimator:
        return self.watcher.repair.lateness

    @property
    def repair_s(self) -> float:
        return self.watcher.repair.repair_s

    @property
    def refresh_s(self) -> float:
        return self.watcher.refresh_s

    @property
    def request_timeout_s(self) -> float:
        return self.watcher.request_timeout_s

    def start(self) -> None:
        self.watcher.start()

    async def aclose(self) -> None:
        await self.watcher.aclose()

    def saw_process(self, robot_id: str, boot: int) -> None:
        self.watcher.saw_process(robot_id, boot)

    def saw_plan(self, robot_id: str, seq: int) -> None:
        self.watcher.saw_plan(robot_id, seq)

    async def heard_from_all(self, timeout: float) -> list[str]:
        return await self.watcher.heard_from_all(timeout)

    async def refresh(self) -> None:
        await self.watcher.refresh()

    async def probe(self, robot_id: str, *, reobserve: bool = True) -> None:
        await self.watcher.probe(robot_id, reobserve=reobserve)

    async def hearsay(self, robot_id: str, about: str, seq: int, asker: str) -> RobotState | None:
        return await self.watcher.hearsay(robot_id, about, seq, asker)

    async def poke(self) -> None:
        await self.watcher.poke()

    async def wait(self, predicate: Callable[[States], bool], timeout: float | None, *,
                   pending: Callable[[States], Collection[str]] | None = None, of: int | None = None) -> States:
        return await self.watcher.wait(predicate, timeout, pending=pending, of=of)

    # The failure detector's part.

    @property
    def down(self) -> dict[str, str]:
        return self.detector.down

    @property
    def down_at(self) -> dict[str, float]:
        return self.detector.down_at

    @property
    def gone(self) -> set[str]:
        return self.detector.gone

    @property
    def alive(self) -> list[str]:
        return self.detector.alive

    @property
    def liveness(self) -> bool:
        return self.detector.liveness

    @property
    def health(self) -> LoopHealth | None:
        return self.detector.health

    @property
    def round_trip(self) -> RttEstimator:
        return self.detector.round_trip

    @property
    def liveness_timeout_s(self) -> float:
        return self.detector.liveness_timeout_s

    @property
    def health_margin_s(self) -> float:
        return self.detector.health_margin_s

    @property
    def confirm_silence(self) -> Callable[[str], Awaitable[bool]] | None:
        return self.detector.confirm_silence

    @confirm_silence.setter
    def confirm_silence(self, ask: Callable[[str], Awaitable[bool]] | None) -> None:
        self.detector.confirm_silence = ask

    async def declare_down(self, robot_id: str, reason: str) -> None:
        await self.detector.declare_down(robot_id, reason)

    async def record_failure(self, robot_id: str, exc: Exception) -> None:
        await self.detector.record_failure(robot_id, exc)
