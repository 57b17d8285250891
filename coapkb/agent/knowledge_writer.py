"""What a robot did, written into the team's knowledge (the Location KB).

The paper keeps the robots' real-time world in the Location KB; these are
the facts a robot's work changes there, each a small SPARQL Update:

* a pick: the object leaves its shelf (its aisle, rack and bin are
  deleted) and ``Picked_by`` the robot ``Picked_at_task`` the task;
* a delivery at the depot: ``Delivered_at_task``, for each object carried;
* an object not at the shelf: its place is deleted, and it is
  ``Missing_since_task`` the task, ``Reported_missing_by`` the robot.

The named query ``pick-place`` reads them back, so a later task for the same
object is skipped by every robot (docs/knowledge.md, "The world in the KB").
Writes go out in order, one at a time, behind the robot's work: a robot
never waits at the shelf for the radio.  A write that fails is tried again a
few times, then dropped with an error in the log (the team still knows the
pick from its decision, and the shelf from the world).
"""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from typing import TYPE_CHECKING, Awaitable, Callable, Iterable

from ..errors import CoapkbError
from ..world import LOCATION_NS

if TYPE_CHECKING:
    from .task_executor import Job

log = logging.getLogger(__name__)

#: Writes waiting for the radio, at most (a robot picks a few objects a
#: minute; a link down for an hour is what this bounds).
QUEUED_MAX = 1000
#: Tries per write, and the wait between two.
WRITE_TRIES = 3
RETRY_S = 2.0

_PLACE = ("Inventory_aisle_no", "Inventory_rack_no", "Inventory_bin_no")


def _iri(name: str) -> str:
    return f"<{LOCATION_NS}{name}>"


def _literal(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _leaves_shelf(obj: str) -> str:
    subject = _iri(obj)
    pattern = " . ".join(f"{subject} {_iri(p)} ?v{i}" for i, p in enumerate(_PLACE))
    return f"DELETE WHERE {{ {pattern} }}"


def pick_update(obj: str, robot: str, seq: int) -> str:
    """The SPARQL Update of a pick: off the shelf, picked by ``robot`` at task ``seq``."""
    subject = _iri(obj)
    return (f"{_leaves_shelf(obj)} ;\nINSERT DATA {{ {subject} {_iri('Picked_by')} {_literal(robot)} . "
            f"{subject} {_iri('Picked_at_task')} {seq} }}")


def missing_update(obj: str, robot: str, seq: int) -> str:
    """The SPARQL Update of an object not at its shelf at task ``seq``."""
    subject = _iri(obj)
    return (f"{_leaves_shelf(obj)} ;\nINSERT DATA {{ {subject} {_iri('Missing_since_task')} {seq} . "
            f"{subject} {_iri('Reported_missing_by')} {_literal(robot)} }}")


def delivered_update(objects: Iterable[tuple[str, int]]) -> str:
    """The SPARQL Update of a delivery: each (object, task) delivered at the depot."""
    facts = " . ".join(f"{_iri(obj)} {_iri('Delivered_at_task')} {seq}" for obj, seq in objects)
    return f"INSERT DATA {{ {facts} }}"


class KnowledgeWriter:
    """Sends a robot's facts with ``write`` (one SPARQL Update each), in order."""

    def __init__(self, write: Callable[[str], Awaitable[None]], retry_s: float = RETRY_S) -> None:
        self._write = write
        self._retry_s = retry_s
        self._queue: deque[str] = deque()
        self._ready = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self.written = 0
        self.dropped = 0

    def picked(self, job: "Job", robot: str) -> None:
        self._enqueue(pick_update(job.object, robot, job.seq))

    def missing(self, job: "Job", robot: str) -> None:
        self._enqueue(missing_update(job.object, robot, job.seq))

    def delivered(self, jobs: Iterable["Job"], robot: str) -> None:
        self._enqueue(delivered_update((job.object, job.seq) for job in jobs))

    def _enqueue(self, update: str) -> None:
        if len(self._queue) >= QUEUED_MAX:
            self._queue.popleft()
            self.dropped += 1
            log.error("more than %d facts wait for the radio: the oldest is dropped", QUEUED_MAX)
        self._queue.append(update)
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
        return len(self._queue)

    async def _run(self) -> None:
        while True:
            await self._ready.wait()
            while self._queue:
                update = self._queue[0]
                for attempt in range(1, WRITE_TRIES + 1):
                    try:
                        await self._write(update)
                        self.written += 1
                        break
                    except CoapkbError as exc:
                        if attempt == WRITE_TRIES:
                            self.dropped += 1
                            log.error("a fact was not written after %d tries: %s", WRITE_TRIES, exc)
                        else:
                            log.warning("a fact was not written (%s); trying again", exc)
                            await asyncio.sleep(self._retry_s)
                if self._queue and self._queue[0] is update:
                    self._queue.popleft()
            self._ready.clear()
