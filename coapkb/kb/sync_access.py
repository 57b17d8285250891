"""Who may replicate a module (docs/knowledge.md, section 7, "Who may
replicate"; docs/security.md, "Replication: only holders"): a sync is taken
only from a robot that holds the module, and only with changes written by
incarnations of its holders.  Pure: the sender comes from the security
layer, the holders from the team's configuration."""

from __future__ import annotations

from collections.abc import Iterator, Mapping

from ..model.deltas import WrittenState
from ..wire.sync import SyncMessage

__all__ = ["SyncAccess", "writer_robot"]


def writer_robot(writer: str) -> str:
    """The robot a writer is an incarnation of: ``Robot1.<boot>`` is
    ``Robot1`` (a name without a numeric incarnation is its own robot)."""
    robot, dot, boot = writer.rpartition(".")
    return robot if dot and robot and boot.isdigit() else writer


def _writers(message: SyncMessage) -> Iterator[str]:
    """Every writer a sync message names: its context's, its deltas' and
    the dots they remove, or a whole state's."""
    yield from message.context.vv
    yield from (d.writer for d in message.context.cloud)
    changes = message.changes
    if isinstance(changes, WrittenState):
        yield from changes.context.vv
        yield from (d.writer for d in changes.context.cloud)
        yield from (d.writer for dots in changes.entries.values() for d in dots)
        yield from (d.writer for d in changes.tombstones)
    elif changes:
        for delta in changes:
            yield delta.dot.writer
            yield from (d.writer for d in delta.removed)


class SyncAccess:
    """Robot ``me``'s rule: ``holding`` names the robots known to hold each
    module, ``known`` the robots whose modules it knows; ``listed``: the
    team's list of holders was given, and a robot it does not list holds
    nothing (without it, a robot of another cluster is unknown)."""

    def __init__(self, me: str, holding: Mapping[str, frozenset[str]], known: frozenset[str], *,
                 listed: bool) -> None:
        self.me = me
        self._holding = dict(holding)
        self._known = known
        self._listed = listed

    def holds(self, robot: str, module: str) -> bool | None:
        """Whether ``robot`` holds ``module``: True, False, or None when this
        robot does not know (a robot of another cluster its configuration
        does not name, without the team's list)."""
        if robot == self.me or robot in self._holding.get(module, ()):
            return True
        if self._listed or robot in self._known:
            return False
        return None

    def refusal(self, message: SyncMessage, sender: str | None) -> str | None:
        """Why ``message`` from ``sender`` (the authenticated member; None:
        unprotected) is not taken, in one line; None if it is."""
        module = message.module
        held = None if sender is None else self.holds(sender, module)
        if held is False:
            return f"{sender} does not hold the {module} module: only its holders replicate it"
        if message.changes is None and held is not True:
            return None  # a question: nothing is taken, nothing kept
        if held is None and sender is not None:
            return (f"{sender} is not a holder of the {module} module that this robot knows: "
                    "only its holders replicate it")
        for writer in set(_writers(message)):
            robot = writer_robot(writer)
            if self.holds(robot, module) is False:
                return f"a change written by {writer}: {robot} does not hold the {module} module"
        return None
