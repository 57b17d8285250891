"""The ground truth of a simulated warehouse: what a robot finds at the shelf.

The knowledge base says where each object is; the world may differ.  An
object can be misplaced (not where the KB says, from the start of the run)
or already taken by another robot (two clusters that decided the same object
before either's write reached the other).  A delivery (:meth:`WorldTruth.restock`)
puts an object back on its shelf.  Everything else is where the
KB says: an operator's write that adds or moves a product is taken to
describe the world, so this keeps only the exceptions.

The truth is consulted the way a robot's sensors would be, at the shelf,
and never by the deciding code.  One instance is shared by every robot of a
run: in the simulator directly, between processes through
:mod:`.service` (a Unix socket, outside the emulated links).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Protocol

#: Objects taken so far that the truth remembers: a shift of 10,000 tasks
#: takes at most that many; beyond this bound the oldest are forgotten
#: (delivered long ago: nobody looks for them on a shelf again).
TAKEN_KEPT = 100_000


@dataclass(frozen=True)
class Taken:
    """Who took an object off its shelf, and for which task."""

    robot: str
    seq: int

    def __str__(self) -> str:
        return f"picked by {self.robot} at task {self.seq}"


class World(Protocol):
    """What a robot's sensors tell it at the shelf."""

    async def take(self, obj: str, robot: str, seq: int) -> str | None:
        """Take ``obj`` off its shelf for task ``seq``: None once it is in the
        robot's hands, else why it is not there."""
        ...


@dataclass
class WorldTruth:
    """The exceptions to the KB's word, and the objects already taken."""

    misplaced: frozenset[str] = frozenset()
    taken: dict[str, Taken] = field(default_factory=dict)
    #: Misplaced objects a robot looked for, and who: a delivery waits for that.
    looked_for: dict[str, Taken] = field(default_factory=dict)
    #: Objects taken that it remembers at most (:data:`TAKEN_KEPT`).
    taken_kept: int = TAKEN_KEPT

    @classmethod
    def with_misplaced(cls, objects: Iterable[str]) -> WorldTruth:
        return cls(misplaced=frozenset(objects))

    def take_now(self, obj: str, robot: str, seq: int) -> str | None:
        """:meth:`World.take`, synchronously: the one place two robots race for an object."""
        if obj in self.misplaced:
            self.looked_for.setdefault(obj, Taken(robot, seq))
            return "not where the KB says it is (misplaced)"
        already = self.taken.get(obj)
        if already is not None:
            return f"gone: {already}"
        self.taken[obj] = Taken(robot, seq)
        while len(self.taken) > self.taken_kept:
            del self.taken[next(iter(self.taken))]
        return None

    async def take(self, obj: str, robot: str, seq: int) -> str | None:
        return self.take_now(obj, robot, seq)

    def restock(self, obj: str) -> None:
        """A delivery: ``obj`` is on its shelf again (returned or new stock),
        where the KB says, whoever took it and wherever it was misplaced."""
        self.taken.pop(obj, None)
        self.looked_for.pop(obj, None)
        if obj in self.misplaced:
            self.misplaced = self.misplaced - {obj}


class KBWorld:
    """A robot with no simulated world: every object is where the KB says."""

    async def take(self, obj: str, robot: str, seq: int) -> str | None:
        return None
