"""What a robot (or the task feeder) knows of the team's states: pushed by
Observe (RFC 7641) on each robot's state resource, never polled.

Liveness comes from the same exchanges: while a wait makes no progress, each
robot is asked once with a plain GET (the refresh below); what the answers
and their absence say is the :class:`~.failure_detector.FailureDetector`'s
to judge.  A down robot is not watched or asked any more until it is
readmitted (:meth:`ObservedStates.readmit`): a restarted process is a new
member, admitted at a task boundary."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable, Collection, Mapping, Sequence

from .. import clock
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
from .notification_repair import NotificationRepair
from .robot_state import RobotState

__all__ = [
    "FAILURES_TO_DOWN", "INDIRECT_PROBES", "INDIRECT_PROBE_TIMEOUTS", "OUTCOME_PATH", "PLAN_PATH", "STATE_PATH",
    "ObservedStates", "States", "indirect_probe", "liveness_floor_s", "liveness_timeout_s",
]

log = logging.getLogger(__name__)

#: Full state: live progress and the last decision (the feeder, people).
STATE_PATH = "/robot/state"
#: Planned state only: all a teammate needs to assign tasks.
PLAN_PATH = "/robot/plan"
#: What the feeder acts on: each decision's outcome and the job queue's
#: standing, notified only when it changes (RobotState.encode_outcome).
OUTCOME_PATH = "/robot/outcome"

States = dict[str, RobotState]

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
    """The latest state of each robot in ``endpoints``, one observation each,
    re-registered whenever it ends (robot not up yet, restarted, or lost).

    A server drops an observation whose notification it could not deliver,
    and the client is not told (RFC 7641 leaves that to Max-Age).  So a wait
    that sees no progress for ``refresh_s`` asks every robot once with a plain
    GET, and re-registers the observations that turned out to be stale."""

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
        self._transport = transport
        self._endpoints = dict(endpoints)
        self._request = Request(Method.GET, path, accept=ContentFormat.CBOR)
        self._refresh_s = refresh_s
        self._request_timeout_s = request_timeout_s
        self.states: States = {}
        self.refreshes = 0
        #: Robot never observed -> the process (``boot``) its decision as the
        #: leader came from: a first state of another process is a restart's.
        self._boot_unseen: dict[str, int] = {}
        self._changed = asyncio.Condition()
        self.detector = FailureDetector(endpoints, self._changed, self._stop_watching, liveness=liveness,
                                        liveness_floor_s=liveness_floor_s, health=health)
        #: Told of every state stored (a recording: coapkb.harness.recording).
        self.listeners: list[Callable[[str, RobotState], None]] = []
        self._watchers: dict[str, asyncio.Task[None]] = {}
        #: The round of liveness GETs in progress (shared), and when the last ended.
        self._refreshing: asyncio.Future[None] | None = None
        self._refreshed_at = 0.0
        #: GETs that repair a lost notification (:meth:`wait`).
        self.repair = NotificationRepair(lambda robot_id: self.probe(robot_id, reobserve=False))

    def start(self) -> None:
        for robot_id in self._endpoints:
            self._start_watch(robot_id)

    def _start_watch(self, robot_id: str) -> None:
        old = self._watchers.get(robot_id)
        if old is not None:
            old.cancel()
        self._watchers[robot_id] = asyncio.create_task(
            self._watch(robot_id, self._endpoints[robot_id]), name=f"observe-{robot_id}"
        )

    def _stop_watching(self, robot_id: str) -> None:
        watcher = self._watchers.pop(robot_id, None)
        if watcher is not None:
            watcher.cancel()

    async def aclose(self) -> None:
        tasks = [*self._watchers.values(), *self.repair.tasks,
                 *([self._refreshing] if self._refreshing is not None else [])]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

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
    def down(self) -> dict[str, str]:
        return self.detector.down

    @property
    def down_at(self) -> dict[str, float]:
        return self.detector.down_at

    @property
    def gone(self) -> set[str]:
        return self.detector.gone

    @property
    def confirm_silence(self) -> Callable[[str], Awaitable[bool]] | None:
        return self.detector.confirm_silence

    @confirm_silence.setter
    def confirm_silence(self, ask: Callable[[str], Awaitable[bool]] | None) -> None:
        self.detector.confirm_silence = ask

    @property
    def liveness_timeout_s(self) -> float:
        return self.detector.liveness_timeout_s

    @property
    def health_margin_s(self) -> float:
        return self.detector.health_margin_s

    @property
    def detection_s(self) -> float:
        """How long a stalled wait may take to find a silent robot down: a
        refresh period, then :data:`FAILURES_TO_DOWN` requests' timeouts and
        an indirect probe's, after the grace a readmitted robot still has
        (its failures do not count before: a process that died before it was
        ever reached is found down only then)."""
        return (self.detector.grace_s + self.refresh_s
                + (FAILURES_TO_DOWN + INDIRECT_PROBE_TIMEOUTS) * self.request_timeout_s + 1.0)

    @property
    def refresh_s(self) -> float:
        return min(self._refresh_s, self.liveness_timeout_s) if self.liveness else self._refresh_s

    @property
    def request_timeout_s(self) -> float:
        return self.liveness_timeout_s if self.liveness else self._request_timeout_s

    @property
    def alive(self) -> list[str]:
        return self.detector.alive

    async def declare_down(self, robot_id: str, reason: str) -> None:
        await self.detector.declare_down(robot_id, reason)

    def readmit(self, robot_id: str) -> None:
        """Count on ``robot_id`` again: a new process of it has joined.  What
        was observed of the old one is forgotten, so the new incarnation's
        state is taken as it comes, not as a restart."""
        self.detector.readmit(robot_id)
        self._boot_unseen.pop(robot_id, None)
        self.states.pop(robot_id, None)
        self._start_watch(robot_id)

    def saw_process(self, robot_id: str, boot: int) -> None:
        """Process ``boot`` of ``robot_id`` sent something here (a decision);
        kept only while no state of it was observed."""
        if robot_id in self._endpoints and robot_id not in self.states:
            self._boot_unseen[robot_id] = boot

    async def revive(self, robot_id: str) -> None:
        """Count on ``robot_id`` again: declared down, it answered as the same
        process (the suspicion was false: this process was the one cut off).
        What was observed of it stays, so a new process of it is still told
        apart by its ``boot`` and found down at once (:meth:`_update`)."""
        if await self.detector.revive(robot_id):
            self._start_watch(robot_id)

    async def heard_from_all(self, timeout: float) -> list[str]:
        """Wait until every robot has been heard from once (its observation
        answered: a security context and a round-trip sample with it), at
        most ``timeout`` s; the robots heard from.  No robot is probed or
        counted down for its silence here: one not up yet is only awaited."""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout), self._changed:
                await self._changed.wait_for(lambda: all(r in self.states for r in self._endpoints))
        return [r for r in self._endpoints if r in self.states]

    async def record_failure(self, robot_id: str, exc: Exception) -> None:
        await self.detector.record_failure(robot_id, exc)

    async def _update(self, robot_id: str, state: RobotState, *, notified: bool = False) -> None:
        """Keep ``robot_id``'s newer ``state``; ``notified``: it came in a
        notification (unasked), not in the answer to a GET."""
        old = self.states.get(robot_id)
        if old is not None and state.boot == old.boot and state.boot and state.plan.seq < old.plan.seq:
            # The same process, an older state: an answer that left before a
            # newer notification and arrived after it (reordered, or a
            # retransmitted request answered again from the exchange cache).
            # Found in the simulator: taken for a restart, it made a robot
            # declare a live teammate down and decide alone.
            return
        if self.liveness and old is not None and (state.boot != old.boot or state.plan.seq < old.plan.seq):
            # A new process that lost the old one's state (a restart): the
            # tasks it was given are gone.  Rejoining is not done, so it stays out.
            await self.detector.restarted(
                robot_id, f"restarted (after task {old.plan.seq} it shows task {state.plan.seq})")
            return
        seen = self._boot_unseen.pop(robot_id, 0) if old is None else 0
        if self.liveness and seen and state.boot and state.boot != seen:
            # Never observed before, but another process of it sent a decision
            # here: this one is a restart.  Found in the simulator: a follower
            # whose observation of its leader was lost took the restarted
            # leader's first state for the old one's, and waited for its
            # decision on a task the new process was never given.
            await self.detector.restarted(robot_id, "restarted (another process than the one that decided before)")
            return
        self.detector.reached(robot_id)
        async with self._changed:
            self.states[robot_id] = state
            self.repair.stored(robot_id, notified=notified)
            self._changed.notify_all()
        for listener in self.listeners:
            listener(robot_id, state)

    async def refresh(self) -> None:
        """GET every robot's state once; re-observe where the observation
        missed a change.  Waits that stall together share one round, and a
        round that ended less than ``refresh_s`` ago counts for them: the
        feeder of a 60-robot team waits for 20 clusters at once, and each
        wait asking all 60 robots made 200 GETs a second."""
        running = self._refreshing
        if running is None or running.done():
            if running is not None and clock.monotonic() - self._refreshed_at < self.refresh_s:
                return
            running = self._refreshing = asyncio.ensure_future(self._probe_all())
        await asyncio.shield(running)

    async def _probe_all(self) -> None:
        self.refreshes += 1
        try:
            await asyncio.gather(*(self.probe(r) for r in self.alive))
        finally:
            self._refreshed_at = clock.monotonic()

    async def probe(self, robot_id: str, *, reobserve: bool = True) -> None:
        """GET ``robot_id``'s state (re-observing if the observation missed a
        change and ``reobserve``); with liveness, failures in a row declare it down."""
        endpoint = self._endpoints[robot_id]
        for _ in range(FAILURES_TO_DOWN if self.liveness else 1):
            started = clock.monotonic()
            try:
                response = await self._transport.request(endpoint, self._request, timeout=self.request_timeout_s)
                state = RobotState.decode(response.payload) if response.status.is_success else None
            except TransportError as exc:
                log.debug("refreshing %s: %s", robot_id, exc)
                await self.detector.failed(robot_id, exc)
                if robot_id in self.detector.down:
                    return
                continue
            except ValueError as exc:
                log.debug("refreshing %s: %s", robot_id, exc)
                return
            self.detector.round_trip.on_sample(clock.monotonic() - started)
            self.detector.heard_from(robot_id)
            self.detector.reached(robot_id)
            if state is not None and state != self.states.get(robot_id):
                await self._update(robot_id, state)
                if reobserve:
                    log.info("observation of %s missed a change; registering again", robot_id)
                    self._start_watch(robot_id)
            return

    async def hearsay(self, robot_id: str, about: str, seq: int) -> RobotState | None:
        """What robot ``robot_id`` has observed of robot ``about`` (``?of=``),
        if it holds ``about``'s plan right after task ``seq`` (``&at=``);
        None if it has not (it then never uses that plan: see
        :meth:`TeamView.forgo`) or does not answer, twice."""
        # A POST: the robot asked goes on without that plan too if it has none.
        request = Request(Method.POST, self._request.path, {"of": about, "at": str(seq)}, accept=ContentFormat.CBOR)
        for _ in range(FAILURES_TO_DOWN):
            try:
                response = await self._transport.request(
                    self._endpoints[robot_id], request, timeout=self.request_timeout_s
                )
                return RobotState.decode(response.payload) if response.status.is_success else None
            except (TransportError, ValueError) as exc:
                log.debug("asking %s about %s: %s", robot_id, about, exc)
                if isinstance(exc, ValueError):  # an answer, but not a state: asking again would not help
                    return None
        return None

    async def poke(self) -> None:
        """Make waits look at the states again (something else they depend on changed)."""
        async with self._changed:
            self._changed.notify_all()

    async def _watch(self, robot_id: str, endpoint: Endpoint) -> None:
        backoff = 0.2
        while True:
            registered = clock.monotonic()
            first = True
            try:
                async for response in self._transport.observe(endpoint, self._request):
                    first_answer = first
                    if first:
                        # The registration is a request and its answer: a
                        # round-trip sample before any probe is needed.
                        self.detector.round_trip.on_sample(clock.monotonic() - registered)
                        first = False
                    if not response.status.is_success:
                        log.warning("%s answered %s on %s", robot_id, response.status.dotted, self._request.path)
                        break
                    try:
                        state = RobotState.decode(response.payload)
                    except ValueError as exc:
                        log.warning("bad state from %s: %s", robot_id, exc)
                        continue
                    backoff = 0.2
                    self.detector.heard_from(robot_id)
                    await self._update(robot_id, state, notified=not first_answer)
            except TransportError as exc:
                log.debug("observing %s: %s", robot_id, exc)
                # A lost observation of a robot seen before counts as a failed
                # request (a dead process's port answers ICMP at once); one not
                # up yet is only awaited.
                if robot_id in self.states:
                    await self.detector.failed(robot_id, exc)
                    if robot_id in self.detector.down:
                        return
            # Not up yet, or the observation ended: register again shortly.
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2, 2.0)

    async def wait(self, predicate: Callable[[States], bool], timeout: float | None, *,
                   pending: Callable[[States], Collection[str]] | None = None, of: int | None = None) -> States:
        """Wait until ``predicate(states)`` holds; TimeoutError after ``timeout`` s (None: no limit).

        ``pending(states)``: the robots whose awaited state has not come; a
        lost notification of one is repaired here (:class:`NotificationRepair`):
        a robot still pending :attr:`NotificationRepair.repair_s` after the
        awaited states became due is asked once with a GET, and again after
        twice as long, and so on (:class:`~.notification_repair.RepairSchedule`:
        ``of``)."""
        async with asyncio.timeout(timeout):
            refresh_at = clock.monotonic() + self.refresh_s
            repair = self.repair.schedule(pending(self.states), of) if pending else None
            while True:
                async with self._changed:
                    if predicate(self.states):
                        if repair is not None and pending is not None:
                            # The last ones to come are samples too (the latest, most of all).
                            repair.came(pending(self.states), clock.monotonic())
                        return dict(self.states)
                    now = clock.monotonic()
                    until = refresh_at
                    if repair is not None and pending is not None:
                        for robot_id in repair.overdue(pending(self.states), now, self.repair.repair_s):
                            if robot_id not in self.detector.down:
                                self.repair.repair(robot_id)
                        until = min(until, repair.next_at)
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(max(0.0, until - now)):
                            await self._changed.wait()
                if clock.monotonic() >= refresh_at:
                    await self.refresh()
                    refresh_at = clock.monotonic() + self.refresh_s

    @property
    def repairs(self) -> int:
        return self.repair.repairs

    @property
    def lateness(self) -> RttEstimator:
        return self.repair.lateness

    @property
    def repair_s(self) -> float:
        return self.repair.repair_s
