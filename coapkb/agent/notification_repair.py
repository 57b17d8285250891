"""Lost notifications repaired.  Notifications go unconfirmed
(NotificationTypes), so a state a wait awaits that is later than states
lately came is asked for with one GET, and again after twice as long, and
so on (:class:`RepairSchedule`); how late states come unasked is measured
as RFC 6298 measures round trips (:attr:`NotificationRepair.repair_s`)."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable, Collection, Coroutine
from typing import Any

from .. import clock
from ..transport.rtt import RttEstimator

#: The least time an awaited state may be late before it is asked for, and
#: the time before any state's lateness was measured.  At 0.2 s before any
#: sample, runs with 100 ms of one-way delay took 9.2-11.7 s where 0.5 s took
#: 13.3-16.2 s.
REPAIR_FLOOR_S = 0.2
INITIAL_REPAIR_S = 0.2
#: The most an awaited state may be late before it is asked for: one state
#: held up by a query's retries (9 s at 20 % loss and 100 ms of delay) is
#: a sample that lifted the estimate to seconds, and the next lost
#: notifications waited that long (completions of 26-45 s against 13-20 s).
REPAIR_CEILING_S = 1.0


class NotificationRepair:
    """The GETs that repair lost notifications (``ask(robot)`` sends one and
    takes the answer), and how late the states that came unasked were."""

    def __init__(self, ask: Callable[[str], Coroutine[Any, Any, None]]) -> None:
        self._ask = ask
        #: The GETs under way, per robot, and how many were sent.
        self._repairing: dict[str, asyncio.Task[None]] = {}
        self.repairs = 0
        #: Robots whose latest state came in a notification (unasked).
        self._notified: set[str] = set()
        #: How late awaited states came, unasked, after they became due (:attr:`repair_s`).
        self.lateness = RttEstimator()

    @property
    def tasks(self) -> list[asyncio.Task[None]]:
        """The GETs sent (to cancel when the states are no longer watched)."""
        return list(self._repairing.values())

    def stored(self, robot_id: str, *, notified: bool) -> None:
        """A state of ``robot_id`` was stored; ``notified``: it came in a
        notification (unasked), not in the answer to a GET."""
        if notified:
            self._notified.add(robot_id)
        else:
            self._notified.discard(robot_id)

    def schedule(self, pending: Collection[str], of: int | None) -> RepairSchedule:
        """The schedule of one wait for the states of ``pending`` (see :class:`RepairSchedule`)."""
        return RepairSchedule(pending, of, self.lateness.on_sample, self._notified.__contains__)

    @property
    def repair_s(self) -> float:
        """How long an awaited state may be late before it is asked for: how
        late the states that came unasked were (from when they became due),
        smoothed as RFC 6298 smooths round trips, plus twice their variation
        (RFC 6298 adds four: a timer that fires early here costs one GET,
        one that fires late holds the whole cluster), at least
        :data:`REPAIR_FLOOR_S` and at most :data:`REPAIR_CEILING_S`
        (:data:`INITIAL_REPAIR_S` before any sample).  Their lateness,
        not a round trip: it holds the spread of the robots' decisions,
        which the links' delay only adds to; the round trips this process
        measures start with a security handshake each."""
        late = self.lateness
        if late.srtt is None:
            return INITIAL_REPAIR_S
        return min(REPAIR_CEILING_S, max(REPAIR_FLOOR_S, late.srtt + 2 * late.rttvar))

    def repair(self, robot_id: str) -> None:
        """GET ``robot_id``'s state once, unless a GET of it is under way;
        the observation stays (a NON notification lost is no sign that it ended)."""
        running = self._repairing.get(robot_id)
        if running is None or running.done():
            self.repairs += 1
            self._repairing[robot_id] = asyncio.create_task(self._ask(robot_id), name=f"repair-{robot_id}")


class RepairSchedule:
    """When each robot a wait still awaits is next asked for its state; tells
    ``on_lateness`` how late each state that came unasked was.

    The awaited states are due once fewer than ``of`` are pending (one of
    that many robots has come: they decide alike), and at once without
    ``of`` (this process already has its own)."""

    def __init__(self, pending: Collection[str], of: int | None, on_lateness: Callable[[float], None],
                 notified: Callable[[str], bool]) -> None:
        self._waiting = set(pending)
        self._of = of
        self._due_at = clock.monotonic() if of is None or len(pending) < of else None
        self._on_lateness = on_lateness
        #: Whether a robot's state came in a notification, not a GET's answer.
        self._notified = notified
        self._asked: dict[str, tuple[float, float]] = {}  # robot -> (when next, the wait before that)
        self.next_at = math.inf

    def came(self, pending: Collection[str], now: float) -> None:
        """Note the states that came since the last look (``pending``: the
        robots still awaited): each that came unasked after it was due is a
        sample of how late states come."""
        if self._due_at is None and self._of is not None and len(pending) < self._of:
            self._due_at = now  # the first awaited state came: the rest are due
        elif self._due_at is not None:
            for robot_id in self._waiting.difference(pending):
                # A notification that came after its GET left is a sample all
                # the same: it was sent unasked.  Taking none then (as Karn's
                # algorithm skips ambiguous round trips) left the estimate at
                # its first value whenever that fired before the states came:
                # with 100 ms of delay every state was asked for, 10 % more bytes.
                # A state the GET brought is no sample: its notification was lost.
                if robot_id not in self._asked or self._notified(robot_id):
                    self._on_lateness(now - self._due_at)
        self._waiting.intersection_update(pending)

    def overdue(self, pending: Collection[str], now: float, repair_s: float) -> list[str]:
        """The robots of ``pending`` to ask now; sets :attr:`next_at`."""
        self.came(pending, now)
        self.next_at = math.inf
        if self._due_at is None:
            return []
        ask = []
        for robot_id in pending:
            at, wait = self._asked.get(robot_id, (self._due_at + repair_s, repair_s))
            if now >= at:
                ask.append(robot_id)
                at, wait = now + 2 * wait, 2 * wait
            self._asked[robot_id] = (at, wait)
            self.next_at = min(self.next_at, at)
        return ask
