"""What a robot (or the task feeder) knows of the team's states: pushed by
Observe (RFC 7641) on each robot's state resource, never polled.

Liveness comes from the same exchanges: while a wait makes no progress, each
robot is asked once with a plain GET (the refresh below); a robot that fails
:data:`FAILURES_TO_DOWN` such requests in a row, each given a timeout that
follows the measured round trip, is declared down.  A down robot is not
watched or asked any more until it is readmitted (:meth:`ObservedStates.readmit`):
a restarted process is a new member, admitted at a task boundary."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable, Collection, Mapping, Sequence

from .. import clock
from ..transport.base import ClientTransport, Endpoint, PeerGone, PeerTimeout, TransportError
from ..transport.messages import ContentFormat, Method, Request
from ..transport.rtt import RttEstimator
from .local_health import LoopHealth
from .notification_repair import NotificationRepair
from .robot_state import RobotState

log = logging.getLogger(__name__)

#: Full state: live progress and the last decision (the feeder, people).
STATE_PATH = "/robot/state"
#: Planned state only: all a teammate needs to assign tasks.
PLAN_PATH = "/robot/plan"
#: What the feeder acts on: each decision's outcome and the job queue's
#: standing, notified only when it changes (RobotState.encode_outcome).
OUTCOME_PATH = "/robot/outcome"

States = dict[str, RobotState]

#: Failed requests in a row after which a robot is declared down: one lost
#: datagram or one busy moment must not remove a live teammate.
FAILURES_TO_DOWN = 2
#: Teammates asked to reach a robot this one finds silent before it is
#: declared down (SWIM's indirect probe), and the probe's time, in request
#: timeouts (the helper's own request to it, and the answer).
INDIRECT_PROBES = 2
INDIRECT_PROBE_TIMEOUTS = 2
#: Turns of the event loop one exchange takes (send, receive, the handlers
#: in between): how often a late loop's lateness adds up in one request.
TURNS_PER_EXCHANGE = 8


def liveness_floor_s(link_kbps: float | None) -> float:
    """The shortest liveness timeout: 1 s on loopback or an unknown link; on a
    known slow radio link (emulated in the benchmarks) 5 s, so two requests
    lost in a row on a lossy link do not remove a live teammate."""
    return 1.0 if link_kbps is None else 5.0


def liveness_timeout_s(round_trip: RttEstimator, floor_s: float) -> float:
    """How long one liveness request may take before it counts as failed:
    four smoothed round trips with their variation, never under ``floor_s``
    (a robot busy with a query answers late on a loaded machine; loopback
    round trips are ~1 ms); twice the floor before any sample."""
    if round_trip.srtt is None:
        return 2 * floor_s
    return max(floor_s, 4 * (round_trip.srtt + 4 * round_trip.rttvar))


async def indirect_probe(transport: ClientTransport, helpers: Sequence[Endpoint], robot_id: str,
                         request_timeout_s: float) -> bool:
    """Whether one of the first :data:`INDIRECT_PROBES` ``helpers`` reaches
    ``robot_id`` now (``GET /robot/plan?probe=ROBOT`` on each, at once)."""
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
        #: This process's own loop lateness (local health): stretches the
        #: liveness timeouts, and failures while the loop ran late do not count.
        self.health = health
        self._endpoints = dict(endpoints)
        self._request = Request(Method.GET, path, accept=ContentFormat.CBOR)
        self._refresh_s = refresh_s
        self._request_timeout_s = request_timeout_s
        #: With liveness, stalled waits refresh (and so probe) after a few
        #: round trips instead of ``refresh_s``, and failures declare robots down.
        self.liveness = liveness
        #: The liveness requests' round trip (RFC 6298).
        self.round_trip = RttEstimator()
        self._liveness_floor_s = liveness_floor_s
        self.states: States = {}
        self.refreshes = 0
        #: Robots declared down: robot id -> why, and when (monotonic seconds).
        self.down: dict[str, str] = {}
        self.down_at: dict[str, float] = {}
        #: Robots down whose process is known gone (nobody listens at its
        #: address, or a new process answers there), not merely silent.
        self.gone: set[str] = set()
        self._failures: dict[str, int] = {}
        #: Robot -> when an answer or a notification of it last arrived.
        self._heard_at: dict[str, float] = {}
        #: Readmitted robot -> until when its failed requests do not count.
        self._joining: dict[str, float] = {}
        #: Robot never observed -> the process (``boot``) its decision as the
        #: leader came from: a first state of another process is a restart's.
        self._boot_unseen: dict[str, int] = {}
        self._changed = asyncio.Condition()
        #: Told of every state stored (a recording: coapkb.harness.recording).
        self.listeners: list[Callable[[str, RobotState], None]] = []
        self._watchers: dict[str, asyncio.Task[None]] = {}
        #: Asks other members whether they reach a robot this process finds
        #: silent (SWIM's indirect probe): True if one does.  None: no one to ask.
        self.confirm_silence: Callable[[str], Awaitable[bool]] | None = None
        self._confirming: dict[str, asyncio.Future[bool]] = {}
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

    async def aclose(self) -> None:
        tasks = [*self._watchers.values(), *self.repair.tasks,
                 *([self._refreshing] if self._refreshing is not None else [])]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    @property
    def liveness_timeout_s(self) -> float:
        return self._on_time_timeout_s + self.health_margin_s

    @property
    def _on_time_timeout_s(self) -> float:
        """The liveness timeout of a process whose loop runs on time."""
        return liveness_timeout_s(self.round_trip, self._liveness_floor_s)

    @property
    def health_margin_s(self) -> float:
        """What this process's own lateness adds to a liveness timeout: an
        exchange takes several turns of the loop, each as late as the loop
        lately was (0 when it runs on time, or nothing measures it)."""
        if self.health is None:
            return 0.0
        return TURNS_PER_EXCHANGE * self.health.late_within(2 * self._on_time_timeout_s)

    @property
    def detection_s(self) -> float:
        """How long a stalled wait may take to find a silent robot down: a
        refresh period, then :data:`FAILURES_TO_DOWN` requests' timeouts,
        after the grace a readmitted robot still has (its failures do not
        count before: a process that died before it was ever reached is
        found down only then)."""
        grace = max(self._joining.values(), default=0.0) - clock.monotonic()
        return max(0.0, grace) + self.refresh_s + (FAILURES_TO_DOWN + INDIRECT_PROBE_TIMEOUTS) * self.request_timeout_s + 1.0

    @property
    def refresh_s(self) -> float:
        return min(self._refresh_s, self.liveness_timeout_s) if self.liveness else self._refresh_s

    @property
    def request_timeout_s(self) -> float:
        return self.liveness_timeout_s if self.liveness else self._request_timeout_s

    @property
    def alive(self) -> list[str]:
        return [r for r in self._endpoints if r not in self.down]

    async def declare_down(self, robot_id: str, reason: str) -> None:
        """Stop counting on ``robot_id``: waits re-evaluate without it."""
        if robot_id in self.down:
            return
        log.warning("%s is down: %s", robot_id, reason)
        async with self._changed:
            self.down[robot_id] = reason
            self.down_at[robot_id] = clock.monotonic()
            self._changed.notify_all()
        watcher = self._watchers.pop(robot_id, None)
        if watcher is not None:
            watcher.cancel()

    def readmit(self, robot_id: str) -> None:
        """Count on ``robot_id`` again: a new process of it has joined.  What
        was observed of the old one is forgotten, so the new incarnation's
        state is taken as it comes, not as a restart."""
        self.down.pop(robot_id, None)  # down_at stays: when the old process was found dead
        self.gone.discard(robot_id)
        self._failures.pop(robot_id, None)
        self._boot_unseen.pop(robot_id, None)
        # For a while, failed requests do not count: reaching the new process
        # takes a new security handshake first (OSCORE: the first requests
        # meet a context that is gone, and EDHOC runs again).
        self._joining[robot_id] = clock.monotonic() + FAILURES_TO_DOWN * 2 * self.liveness_timeout_s
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
        if robot_id not in self.down:
            return
        log.warning("%s answers again as the same process: counted on again", robot_id)
        async with self._changed:
            del self.down[robot_id]
            self.gone.discard(robot_id)
            self._failures.pop(robot_id, None)
            self._changed.notify_all()
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
        """A request to ``robot_id`` made elsewhere (a query) failed at the transport."""
        if robot_id in self._endpoints and robot_id not in self.down:
            await self._failed(robot_id, exc)

    async def _failed(self, robot_id: str, exc: Exception) -> None:
        if clock.monotonic() < self._joining.get(robot_id, 0.0) and not isinstance(exc, PeerGone):
            # The grace of a readmitted robot covers reaching its new process
            # (a security handshake), not its absence: nobody listening there
            # counts (found in the simulator: a process that died before it joined).
            return
        if isinstance(exc, PeerTimeout) and self.health_margin_s * 2 >= self._on_time_timeout_s:
            # This loop ran late: the request had no fair chance, and the
            # silence may be its own (local health, as Lifeguard's).
            log.info("a request to %s failed while this process ran late (%.2f s a turn): not counted",
                     robot_id, self.health_margin_s / TURNS_PER_EXCHANGE)
            return
        self._failures[robot_id] = failures = self._failures.get(robot_id, 0) + 1
        if self.liveness and failures >= FAILURES_TO_DOWN:
            failed_at = clock.monotonic()
            if not isinstance(exc, PeerGone) and await self._reached_by_others(robot_id):
                # Silence (or an error of this process's own making) here, an
                # answer there: this process's link, loop or state, not the
                # robot (nobody listening, ICMP, needs no confirming).
                log.warning("%s is silent to this robot, but a teammate reaches it: not declared down", robot_id)
                self._failures[robot_id] = 0
                return
            if self._heard_at.get(robot_id, float("-inf")) >= failed_at:
                # It answered this process itself while the probe ran (back
                # from a freeze; the helper's answer was lost): the silence
                # is over.  Found in the simulator: declared down a second
                # after its notifications came again, a robot decided a
                # task alone that its teammates took from it.
                log.warning("%s was heard from again while its silence was confirmed: not declared down", robot_id)
                self._failures[robot_id] = 0
                return
            self._gone_if(robot_id, isinstance(exc, PeerGone))
            await self.declare_down(robot_id, f"{failures} requests failed in a row, the last: {exc}")

    def _gone_if(self, robot_id: str, gone: bool) -> None:
        """About to declare ``robot_id`` down: its process known gone, or
        only silent (:attr:`gone`)."""
        if robot_id not in self.down:
            if gone:
                self.gone.add(robot_id)
            else:
                self.gone.discard(robot_id)

    async def _reached_by_others(self, robot_id: str) -> bool:
        """One indirect probe at a time per robot: concurrent failures share it."""
        if self.confirm_silence is None or robot_id in self.down:
            return False
        pending = self._confirming.get(robot_id)
        if pending is None:
            pending = self._confirming[robot_id] = asyncio.ensure_future(self.confirm_silence(robot_id))
            pending.add_done_callback(lambda _: self._confirming.pop(robot_id, None))
        try:
            return await asyncio.shield(pending)
        except Exception:  # noqa: BLE001 - a probe that failed confirms nothing
            return False

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
            self._gone_if(robot_id, True)
            await self.declare_down(robot_id, f"restarted (after task {old.plan.seq} it shows task {state.plan.seq})")
            return
        seen = self._boot_unseen.pop(robot_id, 0) if old is None else 0
        if self.liveness and seen and state.boot and state.boot != seen:
            # Never observed before, but another process of it sent a decision
            # here: this one is a restart.  Found in the simulator: a follower
            # whose observation of its leader was lost took the restarted
            # leader's first state for the old one's, and waited for its
            # decision on a task the new process was never given.
            self._gone_if(robot_id, True)
            await self.declare_down(robot_id, "restarted (another process than the one that decided before)")
            return
        # Heard from: the grace a readmitted process gets until it can be
        # reached (readmit) is over.  Kept beyond, it hid the new process's
        # own death, and its teammates waited out the plan of a dead robot
        # (found in the simulator: killed again soon after a restart).
        self._joining.pop(robot_id, None)
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
                await self._failed(robot_id, exc)
                if robot_id in self.down:
                    return
                continue
            except ValueError as exc:
                log.debug("refreshing %s: %s", robot_id, exc)
                return
            self.round_trip.on_sample(clock.monotonic() - started)
            self._failures[robot_id] = 0
            self._heard_at[robot_id] = clock.monotonic()
            self._joining.pop(robot_id, None)  # reached: see _update
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
                        self.round_trip.on_sample(clock.monotonic() - registered)
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
                    self._failures[robot_id] = 0
                    self._heard_at[robot_id] = clock.monotonic()
                    await self._update(robot_id, state, notified=not first_answer)
            except TransportError as exc:
                log.debug("observing %s: %s", robot_id, exc)
                # A lost observation of a robot seen before counts as a failed
                # request (a dead process's port answers ICMP at once); one not
                # up yet is only awaited.
                if robot_id in self.states:
                    await self._failed(robot_id, exc)
                    if robot_id in self.down:
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
                            if robot_id not in self.down:
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
