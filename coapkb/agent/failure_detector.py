"""Which teammates are down, found from the exchanges a robot (or the task
feeder) has with them anyway: the observations of their states, their
refreshes and the queries it sends (see :mod:`.state_watcher`).

A robot that fails :data:`FAILURES_TO_DOWN` requests in a row, each given a
timeout that follows the measured round trip, and that no teammate reaches
either (SWIM's indirect probe), is declared down.  A down robot is counted on
again when it answers as the same process (:meth:`FailureDetector.revive`)
or when a new process of it joins (:meth:`FailureDetector.readmit`)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable, Iterable

from .. import clock
from ..transport.base import PeerGone, PeerTimeout
from ..transport.rtt import RttEstimator
from .local_health import LoopHealth

log = logging.getLogger(__name__)

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


class FailureDetector:
    """Which of ``robots`` are down, and why; what counts as a failed request
    and how long one may take.

    ``changed`` is notified when a robot goes down or comes back, so waits on
    the team's states look again; ``stop_watching(robot)`` ends the
    observation of a robot declared down (it is not asked any more)."""

    def __init__(
        self,
        robots: Iterable[str],
        changed: asyncio.Condition,
        stop_watching: Callable[[str], None],
        *,
        liveness: bool = False,
        liveness_floor_s: float = 1.0,
        health: LoopHealth | None = None,
    ) -> None:
        self._robots = tuple(robots)
        self._changed = changed
        self._stop_watching = stop_watching
        #: This process's own loop lateness (local health): stretches the
        #: liveness timeouts, and failures while the loop ran late do not count.
        self.health = health
        #: With liveness, stalled waits refresh (and so probe) after a few
        #: round trips instead of their refresh period, and failures declare robots down.
        self.liveness = liveness
        #: The liveness requests' round trip (RFC 6298).
        self.round_trip = RttEstimator()
        self._liveness_floor_s = liveness_floor_s
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
        #: Asks other members whether they reach a robot this process finds
        #: silent (SWIM's indirect probe): True if one does.  None: no one to ask.
        self.confirm_silence: Callable[[str], Awaitable[bool]] | None = None
        self._confirming: dict[str, asyncio.Future[bool]] = {}

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
    def grace_s(self) -> float:
        """How long the failed requests of the latest readmitted robot still
        do not count (0 when none has that grace left)."""
        return max(0.0, max(self._joining.values(), default=0.0) - clock.monotonic())

    @property
    def alive(self) -> list[str]:
        return [r for r in self._robots if r not in self.down]

    async def declare_down(self, robot_id: str, reason: str) -> None:
        """Stop counting on ``robot_id``: waits re-evaluate without it."""
        if robot_id in self.down:
            return
        log.warning("%s is down: %s", robot_id, reason)
        async with self._changed:
            self.down[robot_id] = reason
            self.down_at[robot_id] = clock.monotonic()
            self._changed.notify_all()
        self._stop_watching(robot_id)

    def readmit(self, robot_id: str) -> None:
        """Count on ``robot_id`` again: a new process of it has joined."""
        self.down.pop(robot_id, None)  # down_at stays: when the old process was found dead
        self.gone.discard(robot_id)
        self._failures.pop(robot_id, None)
        # For a while, failed requests do not count: reaching the new process
        # takes a new security handshake first (OSCORE: the first requests
        # meet a context that is gone, and EDHOC runs again).
        self._joining[robot_id] = clock.monotonic() + FAILURES_TO_DOWN * 2 * self.liveness_timeout_s

    async def revive(self, robot_id: str) -> bool:
        """Count on ``robot_id`` again: declared down, it answered as the same
        process (the suspicion was false: this process was the one cut off).
        Whether it was down (and so is to be watched again)."""
        if robot_id not in self.down:
            return False
        log.warning("%s answers again as the same process: counted on again", robot_id)
        async with self._changed:
            del self.down[robot_id]
            self.gone.discard(robot_id)
            self._failures.pop(robot_id, None)
            self._changed.notify_all()
        return True

    async def restarted(self, robot_id: str, reason: str) -> None:
        """A new process of ``robot_id`` answers, without the old one's state:
        the old process is gone, and this one stays out until readmitted."""
        self._gone_if(robot_id, True)
        await self.declare_down(robot_id, reason)

    def heard_from(self, robot_id: str) -> None:
        """An answer or a notification of ``robot_id`` arrived: its failures in a row are over."""
        self._failures[robot_id] = 0
        self._heard_at[robot_id] = clock.monotonic()

    def reached(self, robot_id: str) -> None:
        """``robot_id`` was reached: the grace a readmitted process gets until
        then (:meth:`readmit`) is over.  Kept beyond, it hid the new process's
        own death, and its teammates waited out the plan of a dead robot
        (found in the simulator: killed again soon after a restart)."""
        self._joining.pop(robot_id, None)

    async def record_failure(self, robot_id: str, exc: Exception) -> None:
        """A request to ``robot_id`` made elsewhere (a query) failed at the transport."""
        if robot_id in self._robots and robot_id not in self.down:
            await self.failed(robot_id, exc)

    async def failed(self, robot_id: str, exc: Exception) -> None:
        """A request to ``robot_id`` failed with ``exc``: with liveness, the
        last of :data:`FAILURES_TO_DOWN` in a row declares it down, unless a
        teammate still reaches it or it was heard from meanwhile."""
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

    def failures_in_a_row(self, robot_id: str) -> int:
        """The requests to ``robot_id`` that failed since it was last heard from."""
        return self._failures.get(robot_id, 0)

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
