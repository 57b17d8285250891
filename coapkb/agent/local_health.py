"""Local health: does this process's own event loop run late?

A robot runs path planning, localisation and perception beside coapkb; when
they take the CPU, its event loop turns late, its timers fire late and the
answers it is waiting for sit unread in the socket.  Its requests then time
out although its teammates answered in time, and a failure detector that
counts those timeouts blames the teammates (a false suspicion).  Lifeguard
(HashiCorp memberlist) answers this with local health awareness: a member
that notices its own lateness stretches its timeouts and does not blame its
peers for it.

:class:`LoopHealth` measures the lateness: a ticker asks to wake every
``period_s`` and notes how much later it woke.  :meth:`LoopHealth.late_within`
is the worst lateness seen in a recent window; the failure detector does not
count a failed request against a peer while its own loop ran that late
(see :class:`~coapkb.agent.failure_detector.FailureDetector`).
"""

from __future__ import annotations

import asyncio
import collections
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from .. import clock

#: How often the ticker wakes, seconds: its own cost, against how fine the reading is.
TICK_S = 0.25
#: Lateness samples kept (a minute at TICK_S).
SAMPLES_KEPT = 240


@dataclass(frozen=True)
class LatenessStats:
    """The loop's lateness so far: what ``/robot/stats`` reports."""

    ticks: int
    #: Ticks at least half a tick late.
    late_ticks: int
    max_s: float
    p99_s: float

    def as_dict(self) -> dict[str, float | int]:
        return {"ticks": self.ticks, "late_ticks": self.late_ticks, "max_s": self.max_s, "p99_s": self.p99_s}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> LatenessStats:
        return cls(int(data.get("ticks", 0)), int(data.get("late_ticks", 0)), float(data.get("max_s", 0.0)),
                   float(data.get("p99_s", 0.0)))


class LoopHealth:
    """The running loop's lateness, measured by a ticker (:meth:`start`)."""

    def __init__(self, period_s: float = TICK_S) -> None:
        self.period_s = period_s
        #: (when the tick was due, how late it woke), newest last.
        self._recent: collections.deque[tuple[float, float]] = collections.deque(maxlen=SAMPLES_KEPT)
        self._ticks = 0
        self._late_ticks = 0
        self._max = 0.0
        self._task: asyncio.Task[None] | None = None

    def start(self) -> None:
        self._task = asyncio.create_task(self._tick(), name="loop-health")

    async def aclose(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)

    async def _tick(self) -> None:
        while True:
            due = clock.monotonic() + self.period_s
            await asyncio.sleep(self.period_s)
            self.note(due, clock.monotonic() - due)

    def note(self, due: float, late_s: float) -> None:
        """A wake-up due at ``due`` came ``late_s`` seconds late."""
        late_s = max(0.0, late_s)
        self._recent.append((due, late_s))
        self._ticks += 1
        self._max = max(self._max, late_s)
        if late_s >= self.period_s / 2:
            self._late_ticks += 1

    def late_within(self, window_s: float) -> float:
        """The worst lateness of the ticks due in the last ``window_s`` seconds
        (and of the tick in progress, if it is overdue now)."""
        now = clock.monotonic()
        worst = 0.0
        for due, late in reversed(self._recent):
            if due < now - window_s:
                break
            worst = max(worst, late)
        if self._recent:
            # A tick not yet run: the loop may be late right now.
            pending = now - (self._recent[-1][0] + self._recent[-1][1]) - self.period_s
            worst = max(worst, pending)
        return worst

    def stalled_within(self, window_s: float) -> float:
        """The longest stall (a tick's lateness) that ended in the last
        ``window_s`` seconds, or that lasts still: a process stopped for a
        while finds, once it runs again, that its peers went on without it."""
        now = clock.monotonic()
        worst = 0.0
        for due, late in self._recent:
            if due + late >= now - window_s:
                worst = max(worst, late)
        if self._recent:
            worst = max(worst, now - (self._recent[-1][0] + self._recent[-1][1]) - self.period_s)
        return worst

    def stats(self) -> LatenessStats:
        lates = sorted(late for _, late in self._recent)
        p99 = lates[min(len(lates) - 1, int(0.99 * len(lates)))] if lates else 0.0
        return LatenessStats(self._ticks, self._late_ticks, round(self._max, 6), round(p99, 6))
