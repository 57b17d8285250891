"""What a robot did, written into the team's knowledge (Location and Capability KBs).

The paper keeps the robots' real-time world in the Location KB ("real time
locations of the robots") and what they can do in the Capability KB; these
are the facts a robot's work changes there, each a small SPARQL Update,
sent by name (:mod:`coapkb.kb.named_updates`: 41-57 bytes, not 152-316):

* a pick: the object leaves its shelf (its aisle, rack and bin are
  deleted) and is ``Picked_by`` the robot ``Picked_at_task`` the task;
* a delivery at the depot: ``Delivered_at_task``, for each object carried;
* an object not at the shelf: its place is deleted, and it is
  ``Missing_since_task`` the task, ``Reported_missing_by`` the robot
  (a delivery, written by the feeder, puts an object back: ``restock``);
* with each of these, where the robot is (``Robot_aisle_no``,
  ``Robot_rack_no``, Location) and, once the job is over, the load it
  carries and its battery's charge (``Robot_load_kg``, ``Robot_charge_wh``,
  Capability), each stamped ``Robot_updated_ms`` (Unix milliseconds).

So a robot writes when its work changes the world, never on a timer: on a
35 kbit/s link a position every second would cost more than the task
itself.  What others decide on (a pick, an object missing) goes at once;
the robot's position, load and charge (the latest wins) and its deliveries
wait up to ``LAZY_S`` for an update of their module to ride with, and go
out when the robot turns idle (docs/knowledge.md, "The world in the KB").
The named queries ``pick-place``, ``robot-positions`` and ``robot-loads``
read them back.  A robot never waits at the shelf for the radio.  A write
that fails is tried again a few times, then dropped with an error in the
log (the team still knows the pick from its decision, and the shelf from
the world).  Every try of a write carries one write id, so a holder that
made it already answers again instead of making it twice
(:mod:`coapkb.kb.write_ids`).
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import secrets
from collections import deque
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import dataclass, field

from ..cancelling import cancel_and_wait
from ..errors import CoapkbError
from ..kb.named_updates import NamedUpdate
from ..kb.write_ids import writer_name
from .job import Job

log = logging.getLogger(__name__)

#: Writes waiting for the radio, at most (a robot picks a few objects a
#: minute; a link down for an hour is what this bounds).
QUEUED_MAX = 1000
#: Tries per write, and the wait between two.
WRITE_TRIES = 3
RETRY_S = 2.0
#: The largest update made of several waiting ones (a robot takes 8 KiB).
MERGED_MAX_BYTES = 4096
#: How long a robot's position, load and charge may wait for an update to
#: ride with: a few tasks' worth on a slow link (docs/knowledge.md).
LAZY_S = 10.0
#: A wait shorter than this is due now (rounding must not make it last forever).
DUE_WITHIN_S = 1e-6
#: How long a robot that has become idle waits for its facts to go out
#: before it says it is idle (the feeder waits for that).
DRAIN_WAIT_S = 5.0


def _robot_at(robot: str, at: tuple[int, int], at_ms: int) -> NamedUpdate:
    """Where a robot is (Location) at ``at_ms``: sent after the facts it rides
    with, once (its properties are single-valued)."""
    return NamedUpdate("robot-at", (robot, at[0], at[1], at_ms))


@dataclass
class _Later:
    """A module's facts that may wait: the robot's latest position (or load
    and charge: single-valued, so only the latest matters) and deliveries."""

    latest: NamedUpdate | None = None
    facts: list[NamedUpdate] = field(default_factory=list)
    #: Loop time since when the oldest of them waits.
    since: float = 0.0

    def parts(self) -> list[NamedUpdate]:
        return self.facts + ([self.latest] if self.latest is not None else [])


class KnowledgeWriter:
    """Sends a robot's facts with ``write(module, update, write_id)``, each
    write under an id of its own from ``new_write_id`` (None: numbered
    under the robot's name and a random token), the same for its every try.

    What others decide on (a pick, an object missing) goes at once, in
    order within its module; the modules' writes go side by side (a robot
    turning idle waits for both: one after the other, it waited for their
    sum); what only describes the robot (its position, load and charge)
    and deliveries wait, up to ``lazy_s`` or until the robot is idle
    (:meth:`flush`), and ride with the next update of their module: a
    robot's position needs no request of its own after every job."""

    def __init__(self, write: Callable[[str, list[NamedUpdate], str], Awaitable[None]], robot: str,
                 wall_ms: Callable[[], int], retry_s: float = RETRY_S, lazy_s: float = LAZY_S,
                 new_write_id: Callable[[], str] | None = None, queued_max: int = QUEUED_MAX,
                 merged_max_bytes: int = MERGED_MAX_BYTES) -> None:
        self._write = write
        self._queued_max = queued_max
        self._merged_max_bytes = merged_max_bytes
        self.robot = robot
        if new_write_id is None:
            count, name = itertools.count(1), writer_name(f"{robot}.{secrets.token_hex(4)}")

            def new_write_id() -> str:
                return f"{name}.{next(count)}"
        self._new_write_id: Callable[[], str] = new_write_id
        self._wall_ms = wall_ms
        self._retry_s = retry_s
        self._lazy_s = lazy_s
        #: (module, update) to send at once, oldest first.
        self._queue: deque[tuple[str, NamedUpdate]] = deque()
        #: module -> what may wait.
        self._later: dict[str, _Later] = {}
        self._flushing = False
        self._ready = asyncio.Event()
        self._drained = asyncio.Event()
        self._drained.set()
        #: Modules with a write being sent, and its sender: one at a time
        #: per module (its facts stay in order), the modules side by side.
        self._sending: dict[str, asyncio.Task[None]] = {}
        self._task: asyncio.Task[None] | None = None
        self.written = 0
        self.dropped = 0

    def picked(self, job: Job) -> None:
        self._wait("Location", latest=_robot_at(self.robot, (job.aisle, job.rack), self._wall_ms()))
        self._now("Location", NamedUpdate("pick", (job.object, self.robot, job.seq)))

    def missing(self, job: Job) -> None:
        self._wait("Location", latest=_robot_at(self.robot, (job.aisle, job.rack), self._wall_ms()))
        self._now("Location", NamedUpdate("missing", (job.object, self.robot, job.seq)))

    def delivered(self, jobs: Iterable[Job], depot: tuple[int, int]) -> None:
        self._wait("Location", facts=[NamedUpdate("delivered", (job.object, job.seq)) for job in jobs],
                   latest=_robot_at(self.robot, depot, self._wall_ms()))

    def load(self, load_kg: float, charge_wh: float) -> None:
        self._wait("Capability", latest=NamedUpdate("load", (self.robot, load_kg, charge_wh, self._wall_ms())))

    def flush(self) -> None:
        """Send what waits now (the robot is idle: nothing else will carry it)."""
        if self._later:
            self._flushing = True
            self._ready.set()

    async def drained(self) -> None:
        """Until nothing waits or is being sent."""
        await self._drained.wait()

    def _now(self, module: str, update: NamedUpdate) -> None:
        if len(self._queue) >= self._queued_max:
            self._queue.popleft()
            self.dropped += 1
            log.error("more than %d facts wait for the radio: the oldest is dropped", self._queued_max)
        self._queue.append((module, update))
        self._drained.clear()
        self._ready.set()

    def _wait(self, module: str, *, facts: Iterable[NamedUpdate] = (), latest: NamedUpdate | None = None) -> None:
        later = self._later.get(module)
        if later is None:
            later = self._later[module] = _Later(since=asyncio.get_running_loop().time())
        for fact in facts:
            if len(later.facts) >= self._queued_max:
                later.facts.pop(0)
                self.dropped += 1
            later.facts.append(fact)
        if latest is not None:
            later.latest = latest
        self._drained.clear()
        self._ready.set()

    def start(self) -> None:
        self._task = asyncio.create_task(self._run(), name="knowledge-writer")

    async def aclose(self) -> None:
        await cancel_and_wait((self._task, *self._sending.values()))

    @property
    def pending(self) -> int:
        """Updates waiting or being sent (a module's waiting facts count as one)."""
        return len(self._queue) + len(self._later) + len(self._sending)

    def _next(self) -> tuple[str, list[NamedUpdate]] | None:
        """What to send now, if anything, of a module with no write being
        sent: the oldest update to send at once, with those after it for the
        same module and the module's waiting facts joined on (one request
        instead of several); else a module's waiting facts once due."""
        for index, (module, first) in enumerate(self._queue):
            if module in self._sending:
                continue
            del self._queue[index]
            # Bounded by what the holder renders, the SPARQL Update it makes.
            parts, size = [first], len(first.text())
            while index < len(self._queue) and self._queue[index][0] == module:
                following = self._queue[index][1]
                if size + len(following.text()) + 3 > self._merged_max_bytes:
                    break
                del self._queue[index]
                parts.append(following)
                size += len(following.text()) + 3
            later = self._later.pop(module, None)
            return module, parts + (later.parts() if later is not None else [])
        now = asyncio.get_running_loop().time()
        for module, later in list(self._later.items()):
            if module not in self._sending and (self._flushing or self._wait_left(later, now) == 0.0):
                del self._later[module]
                return module, later.parts()
        if not self._later:
            self._flushing = False
        return None

    def _due_in(self) -> float | None:
        """How long until a module's waiting facts are due (None: none waits
        but behind a write being sent, whose end wakes the writer)."""
        waiting = [later for module, later in self._later.items() if module not in self._sending]
        if not waiting:
            return None
        now = asyncio.get_running_loop().time()
        return min(self._wait_left(later, now) for later in waiting)

    def _wait_left(self, later: _Later, now: float) -> float:
        """How long ``later`` may still wait; 0.0 once due.  One rule for
        both callers: when the first said 0 and the second, by rounding,
        not yet due, the simulator's clock stood still while the loop spun
        (seed 18055 of the storage and forgery profile)."""
        left = later.since + self._lazy_s - now
        return 0.0 if left <= DUE_WITHIN_S else left

    async def _run(self) -> None:
        while True:
            try:
                async with asyncio.timeout(self._due_in()):
                    await self._ready.wait()
            except TimeoutError:
                pass
            self._ready.clear()
            while (chosen := self._next()) is not None:
                module, updates = chosen
                self._sending[module] = asyncio.create_task(self._send_then_next(module, updates),
                                                            name=f"knowledge-writer {module}")
            if not self._queue and not self._later and not self._sending:
                self._drained.set()

    async def _send_then_next(self, module: str, updates: list[NamedUpdate]) -> None:
        try:
            await self._send(module, updates)
        finally:
            del self._sending[module]
            self._ready.set()  # the module's next write, or drained

    async def _send(self, module: str, updates: list[NamedUpdate]) -> None:
        write_id = self._new_write_id()
        for attempt in range(1, WRITE_TRIES + 1):
            try:
                await self._write(module, updates, write_id)
                self.written += 1
                return
            except CoapkbError as exc:
                if attempt == WRITE_TRIES:
                    self.dropped += 1
                    log.error("a fact of the %s KB was not written after %d tries: %s", module, WRITE_TRIES, exc)
                else:
                    log.warning("a fact of the %s KB was not written (%s); trying again", module, exc)
                    await asyncio.sleep(self._retry_s)
