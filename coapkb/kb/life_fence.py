"""The fence between the lives of a robot kept in memory, so that its
lives can write under one name (``docs/knowledge.md``, section 6, "One
name for the lives of a robot kept in memory").

A robot without a data folder forgets at a restart how far its writer
counted.  It may write on under the name of its earlier lives only if no
holder will ever take a dot of an earlier life that it did not hear of:
such a dot and its own next one would be one dot standing for two writes.
The fence gives that:

* a life that takes the name has a number above every one the holders
  know of that robot, and every sync message it sends carries it;
* a holder keeps the highest life it knows of each robot and refuses
  (4.03, nothing taken) a sync from a lower one: an earlier life's pushes
  still on their way when the next started;
* the next life raises the fence at every holder before it reads each
  one's whole context (one exchange each), so every dot of an earlier life
  that any holder will ever take is among those it read;
* a holder's answer to a question carries the lives it knows, so one that
  restarted learns them at its catch-up, and until an answer told it a
  module's lives (or its catch-up ended) it takes no changes of that
  module from a robot's life (it may not know the fence yet).

Pure: the transport and the exchanges are :mod:`.anti_entropy`'s.
"""

from __future__ import annotations

from collections.abc import Mapping

from ..wire.sync import Life

__all__ = ["LifeFence", "lives_writer"]


def lives_writer(robot: str) -> str:
    """The writer of every life of ``robot`` kept in memory that took its
    lives' name (a start draws boot 1 on, so no life's own name is it)."""
    return f"{robot}.0"


class LifeFence:
    """The highest life this robot knows of each robot, and its own life
    once it writes under its lives' name (None until then)."""

    def __init__(self) -> None:
        self._highest: dict[str, int] = {}
        #: This robot's life, carried by every sync message it sends.
        self.own: Life | None = None
        #: The modules whose holders' lives an answer told this process.
        self.told: set[str] = set()

    @property
    def lives(self) -> Mapping[str, int]:
        """Robot -> the highest life known of it (an answer carries them)."""
        return self._highest

    def highest(self, robot: str) -> int:
        """The highest life known of ``robot`` (0: none)."""
        return self._highest.get(robot, 0)

    def refusal(self, life: Life) -> str | None:
        """Why a sync from ``life`` is not taken, in one line; None if it is."""
        highest = self.highest(life.robot)
        if life.number < highest:
            return f"{life.robot}'s life {life.number} has ended: its life {highest} has started"
        return None

    def raise_to(self, life: Life) -> None:
        """``life`` has started: its robot's lower lives are refused from now on."""
        if life.number > self.highest(life.robot):
            self._highest[life.robot] = life.number

    def learn(self, module: str, lives: Mapping[str, int]) -> None:
        """The lives a holder of ``module`` knows of its holders (its answer)."""
        self.told.add(module)
        for robot, number in lives.items():
            self.raise_to(Life(robot, number))

    def begin(self, robot: str) -> Life:
        """This robot's next life, above every one it knows of its own:
        carried from now on by every sync message it sends."""
        life = Life(robot, self.highest(robot) + 1)
        self.raise_to(life)
        self.own = life
        return life
