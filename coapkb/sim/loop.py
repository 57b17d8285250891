"""Processes on one virtual clock: an asyncio event loop per simulated
process, stepped by a scheduler in global time order.

Each simulated process (a robot, the feeder, the harness) gets its own
:class:`SimLoop`, so its tasks, timers and futures are its own, as in a real
process: freezing it (SIGSTOP) means not stepping its loop, killing it means
never stepping it again, starving it of CPU means stepping it late.  The
loops share a :class:`VirtualClock`: :meth:`Scheduler.run` always steps the
process whose next event is earliest and moves the clock to that event, so
no wall-clock time passes while nothing is ready (a 120 s timeout costs
nothing).  With no sockets and no threads, a run is a pure function of its
inputs and its seed.
"""

from __future__ import annotations

import asyncio
import asyncio.events
import heapq
import random
import selectors
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field
from typing import Any, TypeVar

from ..errors import CoapkbError

T = TypeVar("T")

#: How long a starved process runs, on average, between two pauses (seconds).
RUN_SLICE_S = 0.3


class SimulationError(CoapkbError):
    """The simulated run could not go on: it hung, or ran past its time limit."""


class VirtualClock:
    """Seconds since the simulation began; only the scheduler moves it."""

    def __init__(self) -> None:
        self.now = 0.0


class _NoSelector(selectors.BaseSelector):
    """A simulated process has no file descriptors: nothing to wait on."""

    def register(self, fileobj: Any, events: int, data: Any = None) -> selectors.SelectorKey:
        raise SimulationError("a simulated process cannot wait on a file descriptor")

    def unregister(self, fileobj: Any) -> selectors.SelectorKey:
        raise KeyError(fileobj)

    def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
        return []

    def get_map(self) -> dict[Any, selectors.SelectorKey]:
        return {}


class SimLoop(asyncio.BaseEventLoop):
    """An event loop whose clock is virtual and which runs only when stepped."""

    def __init__(self, clock: VirtualClock, on_error: Callable[[dict[str, Any]], None]) -> None:
        super().__init__()
        self._selector = _NoSelector()
        self._virtual = clock
        self.set_exception_handler(lambda _loop, context: on_error(context))

    def time(self) -> float:
        return self._virtual.now

    def _process_events(self, event_list: list[Any]) -> None:
        pass

    def _write_to_self(self) -> None:
        pass

    def next_event(self) -> float | None:
        """When this loop next has something to run (None: nothing scheduled)."""
        if self._ready:
            return self._virtual.now
        scheduled = self._scheduled
        while scheduled and scheduled[0]._cancelled:
            heapq.heappop(scheduled)._scheduled = False
            self._timer_cancelled_count -= 1
        return scheduled[0]._when if scheduled else None

    def step(self) -> None:
        """Run what is due now, as one turn of a real loop does."""
        outer = asyncio.events._get_running_loop()  # a test or command may itself run in a loop
        asyncio.events._set_running_loop(self)
        try:
            self._run_once()
        finally:
            asyncio.events._set_running_loop(outer)


@dataclass(eq=False)
class Process:
    """One simulated OS process: a name, a loop, and what faults did to it."""

    name: str
    loop: SimLoop
    #: How many processes of this name ran before it (a restart is the next incarnation).
    incarnation: int = 0
    #: Running, ``frozen`` (SIGSTOP: timers and sockets wait) or ``dead``.
    status: str = "running"
    #: While starved: (mean length of a pause, until when).  The CPU is
    #: taken away in pauses (other work of the robot runs), between slices
    #: of :data:`RUN_SLICE_S` on average; what fell due in a pause runs in
    #: one batch after it, timers and arrivals together, as on a busy machine.
    starved: tuple[float, float] | None = None
    #: The current or next pause: [start, end).
    pause: tuple[float, float] = (float("inf"), float("inf"))
    #: Tasks started in it and not done (held so none is collected while pending).
    tasks: set[asyncio.Task[Any]] = field(default_factory=set)

    def starve(self, mean_pause_s: float, until_s: float, now: float) -> None:
        self.starved = (mean_pause_s, until_s)
        self.pause = (now, now)

    def runnable_at(self, at: float, rng: random.Random) -> float:
        """When an event due at ``at`` can run: after any pause it falls in."""
        if self.starved is None:
            return at
        mean, until = self.starved
        start, end = self.pause
        while at >= end and end < until:  # draw the pauses up to ``at``, lazily and in order
            start = end + rng.expovariate(1.0 / RUN_SLICE_S)
            end = start + rng.expovariate(1.0 / mean)
        self.pause = (start, end)
        if end >= until and at >= until:
            self.starved = None
            return at
        return end if start <= at < end else at

    def hold(self, task: asyncio.Task[T]) -> asyncio.Task[T]:
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)
        return task

    @property
    def alive(self) -> bool:
        return self.status != "dead"


class Scheduler:
    """Steps the processes' loops in global time order on one clock."""

    def __init__(self, rng: random.Random, trace: Callable[[str], None]) -> None:
        self.clock = VirtualClock()
        self.rng = rng
        self._trace = trace
        self.processes: list[Process] = []
        #: Exceptions that escaped a task of a live process (a protocol bug).
        self.crashes: list[str] = []
        self.steps = 0

    def spawn(self, name: str) -> Process:
        """A new process named ``name`` (a restarted robot is a new process of the same name)."""
        incarnation = sum(1 for p in self.processes if p.name == name)
        process = Process(name, SimLoop(self.clock, lambda context: self._crashed(name, context)), incarnation)
        self.processes.append(process)
        return process

    def start(self, process: Process, coroutine: Coroutine[Any, Any, T]) -> asyncio.Task[T]:
        """Start ``coroutine`` as a task of ``process``."""
        return process.hold(process.loop.create_task(coroutine))

    def _crashed(self, name: str, context: dict[str, Any]) -> None:
        if not any(p.name == name and p.alive for p in self.processes):
            return  # a dead process's abandoned tasks
        exception = context.get("exception")
        what = f"{type(exception).__name__}: {exception}" if exception is not None else context.get("message", "?")
        self.crashes.append(f"{name}: {context.get('message', '')} {what}".strip())
        self._trace(f"crash {name} {what}")

    def kill(self, process: Process) -> None:
        process.status = "dead"

    def freeze(self, process: Process) -> None:
        if process.status == "running":
            process.status = "frozen"

    def resume(self, process: Process) -> None:
        if process.status == "frozen":
            process.status = "running"

    def shutdown(self) -> None:
        """End every process: its tasks cancelled and given the turns their
        cleanup needs (no time passes), the rest closed; then its loop."""
        for process in self.processes:
            process.status = "dead"
        for process in self.processes:
            loop = process.loop
            for task in asyncio.all_tasks(loop):
                task.cancel()
            for _ in range(100):
                if not loop._ready:
                    break
                loop.step()
            for task in asyncio.all_tasks(loop):
                task.get_coro().close()
            loop._ready.clear()
            loop._scheduled.clear()
            loop.close()

    def _next(self) -> tuple[Process | None, float]:
        best: Process | None = None
        best_at = float("inf")
        for process in self.processes:
            if process.status != "running":
                continue
            at = process.loop.next_event()
            if at is None:
                continue
            at = process.runnable_at(at, self.rng)
            if at < best_at:
                best, best_at = process, at
        return best, best_at

    def run(self, done: Callable[[], bool], limit_s: float) -> None:
        """Step the processes until ``done()``; :class:`SimulationError` if
        nothing is left to run first (a hang) or the clock passes ``limit_s``."""
        clock = self.clock
        while not done():
            process, at = self._next()
            if process is None:
                raise SimulationError(f"hung at {clock.now:.3f} s: every process waits and no timer is set")
            if at > limit_s:
                clock.now = limit_s
                raise SimulationError(f"still running after {limit_s:g} simulated seconds")
            clock.now = max(clock.now, at)
            process.loop.step()
            self.steps += 1
