"""What a robot did, written into the team's knowledge (Location and Capability KBs).

The paper keeps the robots' real-time world in the Location KB ("real time
locations of the robots") and what they can do in the Capability KB; these
are the facts a robot's work changes there, each a small SPARQL Update:

* a pick: the object leaves its shelf (its aisle, rack and bin are
  deleted) and is ``Picked_by`` the robot ``Picked_at_task`` the task;
* a delivery at the depot: ``Delivered_at_task``, for each object carried;
* an object not at the shelf: its place is deleted, and it is
  ``Missing_since_task`` the task, ``Reported_missing_by`` the robot
  (a delivery, written by the feeder, puts an object back: :func:`restock_update`);
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

from ..errors import CoapkbError
from ..kb.write_ids import writer_name
from ..world import CAPABILITY_NS, LOCATION_NS
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
#: How long a robot that has become idle waits for its facts to go out
#: before it says it is idle (the feeder waits for that).
DRAIN_WAIT_S = 5.0

_PLACE = ("Inventory_aisle_no", "Inventory_rack_no", "Inventory_bin_no")


def _iri(name: str) -> str:
    """A name of the module the update is for: its namespace is the empty
    prefix (:data:`PROLOGUE`), so a name costs its own length on the radio."""
    return f":{name}"


def _literal(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _number(value: float) -> str:
    """A decimal literal (``Robot_payload``'s datatype; SPARQL's ``1.5``): never an exponent."""
    return f"{value:.3f}"


def _leaves_shelf(obj: str) -> str:
    pattern = " ; ".join(f"{_iri(p)} ?v{i}" for i, p in enumerate(_PLACE))
    return f"DELETE WHERE {{ {_iri(obj)} {pattern} }}"


def pick_update(obj: str, robot: str, seq: int) -> str:
    """The SPARQL Update of a pick: off the shelf, picked by ``robot`` at task ``seq``."""
    return (f"{_leaves_shelf(obj)} ;\nINSERT DATA {{ {_iri(obj)} {_iri('Picked_by')} {_literal(robot)} ; "
            f"{_iri('Picked_at_task')} {seq} }}")


def missing_update(obj: str, robot: str, seq: int) -> str:
    """The SPARQL Update of an object not at its shelf at task ``seq``."""
    return (f"{_leaves_shelf(obj)} ;\nINSERT DATA {{ {_iri(obj)} {_iri('Missing_since_task')} {seq} ; "
            f"{_iri('Reported_missing_by')} {_literal(robot)} }}")


#: What a pick, a delivery and a missing report leave on an object: a restock removes them.
_AFTER_PICK = ("Picked_by", "Picked_at_task", "Delivered_at_task", "Missing_since_task", "Reported_missing_by")


def restock_update(obj: str, place: tuple[int, int, int]) -> str:
    """The SPARQL Update of a delivery (the feeder's, :mod:`coapkb.feeder.restock`):
    ``obj`` back on its shelf at ``place`` (aisle, rack, bin), its pick,
    delivery and missing report gone."""
    deletes = " ;\n".join(f"DELETE WHERE {{ {_iri(obj)} {_iri(p)} ?v }}" for p in (*_AFTER_PICK, *_PLACE))
    values = " ; ".join(f"{_iri(p)} {v}" for p, v in zip(_PLACE, place))
    return f"{deletes} ;\nINSERT DATA {{ {_iri(obj)} {values} }}"


def delivered_update(objects: Iterable[tuple[str, int]]) -> str:
    """The SPARQL Update of a delivery: each (object, task) delivered at the depot."""
    facts = " . ".join(f"{_iri(obj)} {_iri('Delivered_at_task')} {seq}" for obj, seq in objects)
    return f"INSERT DATA {{ {facts} }}"


def robot_at_update(robot: str, at: tuple[int, int], at_ms: int) -> str:
    """The SPARQL Update of where a robot is (Location) at ``at_ms``: sent
    after the facts it rides with, once (its properties are single-valued)."""
    return (f"INSERT DATA {{ {_iri(robot)} {_iri('Robot_aisle_no')} {at[0]} ; {_iri('Robot_rack_no')} {at[1]} ; "
            f"{_iri('Robot_updated_ms')} {at_ms} }}")


def load_update(robot: str, load_kg: float, charge_wh: float, at_ms: int) -> str:
    """The SPARQL Update of a robot's carried load and battery charge (Capability)."""
    return (f"INSERT DATA {{ {_iri(robot)} {_iri('Robot_load_kg')} {_number(load_kg)} ; "
            f"{_iri('Robot_charge_wh')} {_number(charge_wh)} ; {_iri('Robot_updated_ms')} {at_ms} }}")


#: Each module's namespace as the empty prefix: what an update of it starts with.
PROLOGUE = {"Location": f"PREFIX : <{LOCATION_NS}>\n", "Capability": f"PREFIX : <{CAPABILITY_NS}>\n"}


def with_prologue(module: str, update: str) -> str:
    """``update`` (built by this module's functions) as sent: its prologue first."""
    return PROLOGUE[module] + update


@dataclass
class _Later:
    """A module's facts that may wait: the robot's latest position (or load
    and charge: single-valued, so only the latest matters) and deliveries."""

    latest: str | None = None
    facts: list[str] = field(default_factory=list)
    #: Loop time since when the oldest of them waits.
    since: float = 0.0

    def parts(self) -> list[str]:
        return self.facts + ([self.latest] if self.latest is not None else [])


class KnowledgeWriter:
    """Sends a robot's facts with ``write(module, update, write_id)``, each
    write under an id of its own from ``new_write_id`` (None: numbered
    under the robot's name and a random token), the same for its every try.

    What others decide on (a pick, an object missing) goes at once, in
    order; what only describes the robot (its position, load and charge)
    and deliveries wait, up to ``lazy_s`` or until the robot is idle
    (:meth:`flush`), and ride with the next update of their module: a
    robot's position needs no request of its own after every job."""

    def __init__(self, write: Callable[[str, str, str], Awaitable[None]], robot: str,
                 wall_ms: Callable[[], int], retry_s: float = RETRY_S, lazy_s: float = LAZY_S,
                 new_write_id: Callable[[], str] | None = None) -> None:
        self._write = write
        self.robot = robot
        if new_write_id is None:
            count, name = itertools.count(1), writer_name(f"{robot}.{secrets.token_hex(4)}")
            new_write_id = lambda: f"{name}.{next(count)}"  # noqa: E731 - one line, one use
        self._new_write_id = new_write_id
        self._wall_ms = wall_ms
        self._retry_s = retry_s
        self._lazy_s = lazy_s
        #: (module, update) to send at once, oldest first.
        self._queue: deque[tuple[str, str]] = deque()
        #: module -> what may wait.
        self._later: dict[str, _Later] = {}
        self._flushing = False
        self._ready = asyncio.Event()
        self._drained = asyncio.Event()
        self._drained.set()
        self._sending = False
        self._task: asyncio.Task[None] | None = None
        self.written = 0
        self.dropped = 0

    def picked(self, job: Job) -> None:
        self._wait("Location", latest=robot_at_update(self.robot, (job.aisle, job.rack), self._wall_ms()))
        self._now("Location", pick_update(job.object, self.robot, job.seq))

    def missing(self, job: Job) -> None:
        self._wait("Location", latest=robot_at_update(self.robot, (job.aisle, job.rack), self._wall_ms()))
        self._now("Location", missing_update(job.object, self.robot, job.seq))

    def delivered(self, jobs: Iterable[Job], depot: tuple[int, int]) -> None:
        self._wait("Location", fact=delivered_update((job.object, job.seq) for job in jobs),
                   latest=robot_at_update(self.robot, depot, self._wall_ms()))

    def load(self, load_kg: float, charge_wh: float) -> None:
        self._wait("Capability", latest=load_update(self.robot, load_kg, charge_wh, self._wall_ms()))

    def flush(self) -> None:
        """Send what waits now (the robot is idle: nothing else will carry it)."""
        if self._later:
            self._flushing = True
            self._ready.set()

    async def drained(self) -> None:
        """Until nothing waits or is being sent."""
        await self._drained.wait()

    def _now(self, module: str, update: str) -> None:
        if len(self._queue) >= QUEUED_MAX:
            self._queue.popleft()
            self.dropped += 1
            log.error("more than %d facts wait for the radio: the oldest is dropped", QUEUED_MAX)
        self._queue.append((module, update))
        self._drained.clear()
        self._ready.set()

    def _wait(self, module: str, *, fact: str | None = None, latest: str | None = None) -> None:
        later = self._later.get(module)
        if later is None:
            later = self._later[module] = _Later(since=asyncio.get_running_loop().time())
        if fact is not None:
            if len(later.facts) >= QUEUED_MAX:
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
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass

    @property
    def pending(self) -> int:
        """Updates waiting or being sent (a module's waiting facts count as one)."""
        return len(self._queue) + len(self._later) + self._sending

    def _next(self) -> tuple[str, str] | None:
        """What to send now, if anything: the oldest update to send at once,
        with those after it for the same module and the module's waiting
        facts joined on (one request instead of several); else a module's
        waiting facts once due."""
        if self._queue:
            module, first = self._queue.popleft()
            parts, size = [first], len(first)
            while self._queue and self._queue[0][0] == module:
                following = self._queue[0][1]
                if size + len(following) + 3 > MERGED_MAX_BYTES:
                    break
                self._queue.popleft()
                parts.append(following)
                size += len(following) + 3
            later = self._later.pop(module, None)
            return module, " ;\n".join(parts + (later.parts() if later is not None else []))
        now = asyncio.get_running_loop().time()
        for module, later in list(self._later.items()):
            if self._flushing or now - later.since >= self._lazy_s:
                del self._later[module]
                return module, " ;\n".join(later.parts())
        self._flushing = False
        return None

    def _due_in(self) -> float | None:
        if not self._later:
            return None
        now = asyncio.get_running_loop().time()
        return max(0.0, min(later.since for later in self._later.values()) + self._lazy_s - now)

    async def _run(self) -> None:
        while True:
            try:
                async with asyncio.timeout(self._due_in()):
                    await self._ready.wait()
            except TimeoutError:
                pass
            self._ready.clear()
            while (chosen := self._next()) is not None:
                module, update = chosen
                self._sending = True
                try:
                    await self._send(module, update)
                finally:
                    self._sending = False
            if not self._queue and not self._later:
                self._drained.set()

    async def _send(self, module: str, update: str) -> None:
        write_id = self._new_write_id()
        for attempt in range(1, WRITE_TRIES + 1):
            try:
                await self._write(module, with_prologue(module, update), write_id)
                self.written += 1
                return
            except CoapkbError as exc:
                if attempt == WRITE_TRIES:
                    self.dropped += 1
                    log.error("a fact of the %s KB was not written after %d tries: %s", module, WRITE_TRIES, exc)
                else:
                    log.warning("a fact of the %s KB was not written (%s); trying again", module, exc)
                    await asyncio.sleep(self._retry_s)
