"""The latest state of each teammate, pushed by Observe (RFC 7641) on its
state resource, never polled, and the waits on those states.

A server drops an observation whose notification it could not deliver, and
the client is not told (RFC 7641 leaves that to Max-Age).  So a wait that
sees no progress for a while asks every robot once with a plain GET (the
refresh), and re-registers the observations that turned out to be stale; a
single awaited state that is late is asked for alone
(:mod:`.notification_repair`).  What these exchanges say of a robot's
liveness is the :class:`~.failure_detector.FailureDetector`'s to judge."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable, Collection, Mapping

from .. import clock
from ..cancelling import cancel_and_wait
from ..transport.base import ClientTransport, Endpoint, TransportError
from ..transport.messages import ContentFormat, Method, Request
from .failure_detector import FAILURES_TO_DOWN, FailureDetector
from .first_sight import FirstSight
from .notification_repair import NotificationRepair
from .robot_state import RobotState

log = logging.getLogger(__name__)

States = dict[str, RobotState]


class StateWatcher:
    """The latest state of each robot in ``endpoints`` (at ``path``), one
    observation each, re-registered whenever it ends (robot not up yet,
    restarted, or lost); ``detector`` is told of every answer and failure,
    and robots it declares down are not watched or asked.  ``changed`` is
    notified of every state stored."""

    def __init__(
        self,
        transport: ClientTransport,
        endpoints: Mapping[str, Endpoint],
        path: str,
        detector: FailureDetector,
        changed: asyncio.Condition,
        *,
        refresh_s: float = 10.0,
        request_timeout_s: float = 10.0,
    ) -> None:
        self._transport = transport
        self._endpoints = dict(endpoints)
        self._request = Request(Method.GET, path, accept=ContentFormat.CBOR)
        self._refresh_s = refresh_s
        self._request_timeout_s = request_timeout_s
        self._detector = detector
        self._changed = changed
        self.states: States = {}
        self.refreshes = 0
        #: What was heard of robots never observed (their process, their plans).
        self._unseen = FirstSight()
        #: Told of every state stored (a recording: coapkb.harness.recording).
        self.listeners: list[Callable[[str, RobotState], None]] = []
        self._watchers: dict[str, asyncio.Task[None]] = {}
        #: The round of liveness GETs in progress (shared), and when the last ended.
        self._refreshing: asyncio.Future[None] | None = None
        self._refreshed_at = 0.0
        self.repair = NotificationRepair(lambda robot_id: self.probe(robot_id, reobserve=False))

    def start(self) -> None:
        for robot_id in self._endpoints:
            self.watch(robot_id)

    def watch(self, robot_id: str) -> None:
        """Observe ``robot_id`` (again: a watch under way is ended first)."""
        old = self._watchers.get(robot_id)
        if old is not None:
            old.cancel()
        self._watchers[robot_id] = asyncio.create_task(
            self._watch(robot_id, self._endpoints[robot_id]), name=f"observe-{robot_id}"
        )

    def stop_watching(self, robot_id: str) -> None:
        """Observe ``robot_id`` no more (declared down)."""
        watcher = self._watchers.pop(robot_id, None)
        if watcher is not None:
            watcher.cancel()

    def forget(self, robot_id: str, boot: int = 0) -> None:
        """Forget what was observed of ``robot_id`` and observe it again: a
        new process of it joined, whose state is taken as it comes, not as a
        restart -- unless ``boot`` names the process that joined, and
        another one answers."""
        self._unseen.forget(robot_id, boot)
        self.states.pop(robot_id, None)
        self.watch(robot_id)

    async def aclose(self) -> None:
        await cancel_and_wait((*self._watchers.values(), *self.repair.tasks, self._refreshing))

    @property
    def refresh_s(self) -> float:
        return min(self._refresh_s, self._detector.liveness_timeout_s) if self._detector.liveness else self._refresh_s

    @property
    def request_timeout_s(self) -> float:
        return self._detector.liveness_timeout_s if self._detector.liveness else self._request_timeout_s

    def saw_process(self, robot_id: str, boot: int) -> None:
        """Process ``boot`` of ``robot_id`` sent something here (a decision);
        kept only while no state of it was observed."""
        if robot_id in self._endpoints and robot_id not in self.states:
            self._unseen.saw_process(robot_id, boot)

    def saw_plan(self, robot_id: str, seq: int) -> None:
        """A plan of ``robot_id`` right after task ``seq`` went into a decision
        this robot carries (its own, or a teammate's taken whole): a process
        of it had decided that far.  Kept only while no state of it was
        observed: plans only grow within a process, so a first state showing
        an earlier one is a restart's."""
        if robot_id in self._endpoints and robot_id not in self.states:
            self._unseen.saw_plan(robot_id, seq)

    async def expect_process(self, robot_id: str, boot: int) -> None:
        """Process ``boot`` of ``robot_id`` is the one counted on: if another
        one's state is here already, that one is a restart (down until it
        joins); if none is, the first state observed is judged by it."""
        state = self.states.get(robot_id)
        if state is None:
            self._unseen.saw_process(robot_id, boot)
        elif self._detector.liveness and state.boot and state.boot != boot:
            await self._detector.restarted(robot_id, "restarted (another process than the one heard of before)")

    async def heard_from_all(self, timeout: float) -> list[str]:
        """Wait until every robot has been heard from once (its observation
        answered: a security context and a round-trip sample with it), at
        most ``timeout`` s; the robots heard from.  No robot is probed or
        counted down for its silence here: one not up yet is only awaited."""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout), self._changed:
                await self._changed.wait_for(lambda: all(r in self.states for r in self._endpoints))
        return [r for r in self._endpoints if r in self.states]

    async def update(self, robot_id: str, state: RobotState, *, notified: bool = False) -> None:
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
        if self._detector.liveness and old is not None and (state.boot != old.boot or state.plan.seq < old.plan.seq):
            # A new process that lost the old one's state (a restart): the
            # tasks it was given are gone.  Rejoining is not done, so it stays out.
            await self._detector.restarted(
                robot_id, f"restarted (after task {old.plan.seq} it shows task {state.plan.seq})")
            return
        if old is None:
            why = self._unseen.restart(robot_id, state)
            if self._detector.liveness and why is not None:
                await self._detector.restarted(robot_id, why)
                return
        self._detector.reached(robot_id)
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
            await asyncio.gather(*(self.probe(r) for r in self._detector.alive))
        finally:
            self._refreshed_at = clock.monotonic()

    async def probe(self, robot_id: str, *, reobserve: bool = True) -> None:
        """GET ``robot_id``'s state (re-observing if the observation missed a
        change and ``reobserve``); with liveness, failures in a row declare it down."""
        endpoint = self._endpoints[robot_id]
        for _ in range(FAILURES_TO_DOWN if self._detector.liveness else 1):
            started = clock.monotonic()
            try:
                response = await self._transport.request(endpoint, self._request, timeout=self.request_timeout_s)
                state = RobotState.decode(response.payload) if response.status.is_success else None
            except TransportError as exc:
                log.debug("refreshing %s: %s", robot_id, exc)
                await self._detector.failed(robot_id, exc)
                if robot_id in self._detector.down:
                    return
                continue
            except ValueError as exc:
                log.debug("refreshing %s: %s", robot_id, exc)
                return
            self._detector.round_trip.on_sample(clock.monotonic() - started)
            self._detector.heard_from(robot_id)
            self._detector.reached(robot_id)
            if state is not None and state != self.states.get(robot_id):
                await self.update(robot_id, state)
                if reobserve:
                    log.info("observation of %s missed a change; registering again", robot_id)
                    self.watch(robot_id)
            return

    async def hearsay(self, robot_id: str, about: str, seq: int, asker: str) -> RobotState | None:
        """What robot ``robot_id`` has observed of robot ``about`` (``?of=``),
        if it holds ``about``'s plan right after task ``seq`` (``&at=``);
        None if it has not (it then never uses that plan: see
        :meth:`.TeamMembership.forgo`) or does not answer, twice.
        ``asker``: the robot asking (``&by=``), whom the one asked may have left out."""
        # A POST: the robot asked goes on without that plan too if it has none.
        query = {"of": about, "at": str(seq), "by": asker}
        request = Request(Method.POST, self._request.path, query, accept=ContentFormat.CBOR)
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
                        self._detector.round_trip.on_sample(clock.monotonic() - registered)
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
                    self._detector.heard_from(robot_id)
                    await self.update(robot_id, state, notified=not first_answer)
            except TransportError as exc:
                log.debug("observing %s: %s", robot_id, exc)
                # A lost observation of a robot seen before counts as a failed
                # request (a dead process's port answers ICMP at once); one not
                # up yet is only awaited.
                if robot_id in self.states:
                    await self._detector.failed(robot_id, exc)
                    if robot_id in self._detector.down:
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
                            if robot_id not in self._detector.down:
                                self.repair.repair(robot_id)
                        until = min(until, repair.next_at)
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(max(0.0, until - now)):
                            await self._changed.wait()
                if clock.monotonic() >= refresh_at:
                    await self.refresh()
                    refresh_at = clock.monotonic() + self.refresh_s
