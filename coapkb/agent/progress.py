"""How often a robot tells its observers about progress on a job.

A robot's live state changes four or five times per pick (travelling,
picking, the job done, unloading, idle).  Each change was one confirmable
notification of ``/robot/state`` to every observer (the feeder, people),
each with the whole state (the last decision included): about a kilobyte
per task on a 35 kbit/s link, most of it for positions nobody acts on.

RFC 7641 lets a server skip intermediate states (section 4.5: only the
newest matters), so :class:`ProgressPacing` sends at once what observers
act on -- a decision, a job done, a job dropped, the robot idle -- and
progress alone at most once per ``pace_s``, with whatever the state is by
then.  The feeder observes ``/robot/outcome`` instead, which is notified
only for what it acts on: progress alone never reaches it.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from ..clock import monotonic as loop_clock
from .robot_state import LiveState

#: Least time between two notifications that carry progress alone, seconds.
PROGRESS_PACE_S = 1.0


def acted_on(before: LiveState, after: LiveState) -> bool:
    """Does the change from ``before`` to ``after`` matter to an observer's
    decisions?  The feeder counts jobs done, sends dropped jobs round again
    and feeds a robot once it is idle; positions and activities are for people."""
    return (
        after.done != before.done
        or after.fenced != before.fenced
        or (after.activity == "idle" and after.queued == 0 and before.activity != "idle")
    )


class ProgressPacing:
    """Calls ``notify`` at once for changes observers act on, and at most once
    per ``pace_s`` for progress alone (the last change wins)."""

    def __init__(self, notify: Callable[[], None], pace_s: float = PROGRESS_PACE_S,
                 clock: Callable[[], float] = loop_clock) -> None:
        self._notify = notify
        self.pace_s = pace_s
        self._clock = clock
        self._last = -float("inf")
        self._pending: asyncio.Handle | None = None
        self._pending_now = False

    def now(self) -> None:
        """Notify now: once the changes made in this turn of the event loop
        are in (a job done and the robot idle are one notification), with
        any progress waiting folded in."""
        if self._pending_now:
            return
        self._schedule(0.0)

    def progress(self) -> None:
        """Progress alone: notify when ``pace_s`` has passed since the last notification."""
        if self._pending is None:  # else the one scheduled carries this change too
            self._schedule(self._last + self.pace_s - self._clock())

    def _schedule(self, wait: float) -> None:
        self.cancel()
        loop = asyncio.get_running_loop()
        self._pending_now = wait <= 0
        self._pending = loop.call_soon(self._fire) if wait <= 0 else loop.call_later(wait, self._fire)

    def _fire(self) -> None:
        self._pending, self._pending_now = None, False
        self._last = self._clock()
        self._notify()

    def cancel(self) -> None:
        if self._pending is not None:
            self._pending.cancel()
            self._pending, self._pending_now = None, False
