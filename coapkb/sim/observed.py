"""What really happened in a simulated run, seen from outside the robots.

The oracles (:mod:`.invariants`) must not take the robots' word for what
they did: a robot whose fence is broken still says it was fenced, and a
world that lets an object be taken twice still answers "picked".  So the
simulator watches three things from where the robots cannot lie:

* the shelf (:class:`Shelf`): every take of an object, whatever the world
  answered, with the robot's process and the simulated time;
* the network (:class:`GrantLog`): every lease a robot granted a teammate,
  read off the answers its server sent;
* the knowledge base (:func:`store_quads`, :func:`written_view`): the
  triples a holder's queries see, compared between holders.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

import pyoxigraph as ox

from ..agent.lease import LEASE_PATH
from ..kb.live import LiveKB
from ..model.results import Triple
from ..transport.messages import Request, Response
from ..world.truth import WorldTruth
from .loop import Process, SimLoop


@dataclass(frozen=True)
class Take:
    """One robot's hand on a shelf: ``taken`` when the object came off it."""

    robot: str
    incarnation: int
    seq: int
    object: str
    at_s: float
    taken: bool
    why: str | None = None


@dataclass(frozen=True)
class Grant:
    """``granter`` answered ``grantee``'s lease request with a grant at ``at_s``."""

    granter: str
    grantee: str
    at_s: float


class Shelf:
    """The world as the robots' sensors meet it, recording every take.

    Wraps the run's :class:`~coapkb.world.truth.WorldTruth` (the one place two
    robots race for an object); what it records is read by the shelf oracle,
    which counts the takes that succeeded per object, not what the world's
    own bookkeeping says."""

    def __init__(self, truth: WorldTruth, processes: Mapping[SimLoop, Process], clock: Callable[[], float]) -> None:
        self.truth = truth
        self._processes = processes
        self._clock = clock
        self.takes: list[Take] = []

    async def take(self, obj: str, robot: str, seq: int) -> str | None:
        why = self.truth.take_now(obj, robot, seq)
        loop = asyncio.get_running_loop()
        process = self._processes.get(loop) if isinstance(loop, SimLoop) else None
        incarnation = process.incarnation if process is not None else 0
        self.takes.append(Take(robot, incarnation, seq, obj, round(self._clock(), 6), why is None, why))
        return why


class GrantLog:
    """Every lease granted, as the granters' servers answered (a hook on the simulated network)."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        self.grants: list[Grant] = []

    def answered(self, server: Process, request: Request, response: Response) -> None:
        if request.path == LEASE_PATH and response.status.is_success and "check" not in request.query:
            self.grants.append(Grant(server.name, request.query.get("r", ""), round(self._clock(), 6)))


def store_quads(live: LiveKB) -> frozenset[ox.Quad]:
    """Every quad ``live``'s queries see now: read from the store that
    answers them, not from the replica's bookkeeping."""
    return frozenset(live.view.store)


def of_module(quads: Iterable[ox.Quad], live: LiveKB, module: str) -> list[ox.Quad]:
    """Those of ``quads`` whose subject is in ``module``'s namespaces."""
    prefixes = tuple(live._namespaces[module])
    return [quad for quad in quads if getattr(quad.subject, "value", "").startswith(prefixes)]


def written_view(live: LiveKB, module: str) -> frozenset[tuple[Triple, bool]]:
    """What ``module``'s writes make of the view at ``live``: each triple a
    write touched (and each file value a single-valued write competes with),
    and whether it shows.  Cheap enough to take many times a run; two
    holders at the same version must give the same."""
    replica = live.replicas[module]
    touched = set(replica.entries) | replica.removed_base
    seen = replica.visibility.snapshot(touched, live._is_base)
    return frozenset(seen.items())
