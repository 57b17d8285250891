"""What really happened in a simulated run, seen from outside the robots.

The oracles (:mod:`.invariants`) must not take the robots' word for what
they did: a robot whose fence is broken still says it was fenced, and a
world that lets an object be taken twice still answers "picked".  So the
simulator watches three things from where the robots cannot lie:

* the shelf (:class:`Shelf`): every take of an object, whatever the world
  answered, with the robot's process and the simulated time;
* the network (:class:`GrantLog`): every lease a robot granted a teammate,
  read off the answers its server sent;
* the knowledge base (:class:`FilesQuads`, :func:`written_view`): the
  triples a holder's queries see, compared between holders.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

import pyoxigraph as ox

from ..agent.lease import LEASE_PATH
from ..kb.live import LiveKB
from ..kb.oxigraph_backend import OxigraphBackend
from ..kb.store import KnowledgeBase
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
        # Neither the feeder's check nor a robot's "do you count me" is a grant.
        if request.path == LEASE_PATH and response.status.is_success and not {"check", "counts"} & set(request.query):
            self.grants.append(Grant(server.name, request.query.get("r", ""), round(self._clock(), 6)))


def store_lines(store: ox.Store) -> frozenset[bytes]:
    """Every quad of ``store`` as its N-Quads line.  pyoxigraph writes the
    whole store at once, and a set of lines is made 1.7x faster than one of
    quads: the end of every run compares each holder's whole store."""
    written = store.dump(format=ox.RdfFormat.N_QUADS)
    assert written is not None  # dump returns the bytes when given no output
    return frozenset(written.splitlines())


def as_quads(lines: Iterable[bytes]) -> frozenset[ox.Quad]:
    """The quads of N-Quads ``lines`` (those two stores differ by: a few)."""
    return frozenset(ox.parse(b"\n".join(lines), format=ox.RdfFormat.N_QUADS))


def of_module(quads: Iterable[ox.Quad], live: LiveKB, module: str) -> frozenset[ox.Quad]:
    """Those of ``quads`` whose subject is in ``module``'s namespaces."""
    prefixes = tuple(live._namespaces[module])
    return frozenset(quad for quad in quads if getattr(quad.subject, "value", "").startswith(prefixes))


class FilesQuads:
    """The quads of each KB's files, and what two holders' files differ by
    in one module: what the end of every run takes away from its holders'
    stores before comparing them.

    Two holders' stores are compared by module; holding other modules, they
    differ by thousands of the files' triples, which the files alone
    explain.  The symmetric difference of the stores is that of what the
    files and the changes since made of each, so it is computed from the
    changes (small) and the files' difference (kept: a simulator process
    loads each KB once, and the files never change).  Stores are compared
    as sets of N-Quads lines (:func:`store_lines`), and only the lines they
    differ by are read back as quads."""

    def __init__(self) -> None:
        # Keyed by the loaded KBs themselves (compared as objects): one per
        # set of files in a simulator process.
        self._lines: dict[KnowledgeBase, frozenset[bytes]] = {}
        self._differences: dict[tuple[KnowledgeBase, KnowledgeBase, str], frozenset[ox.Quad]] = {}

    def lines_of(self, base: KnowledgeBase) -> frozenset[bytes]:
        """Every quad of ``base``'s files, as its N-Quads line."""
        kept = self._lines.get(base)
        if kept is None:
            assert isinstance(base.engine, OxigraphBackend)
            kept = self._lines[base] = store_lines(base.engine.store)
        return kept

    def module_difference(self, a: LiveKB, b: LiveKB, module: str) -> frozenset[ox.Quad]:
        """The quads of ``module`` that the files of ``a`` and ``b`` do not share."""
        if a.base is b.base:
            return frozenset()
        key = (a.base, b.base, module)
        kept = self._differences.get(key)
        if kept is None:
            kept = self._differences[key] = of_module(as_quads(self.lines_of(a.base) ^ self.lines_of(b.base)), a,
                                                      module)
        return kept

    def changed(self, live: LiveKB) -> frozenset[ox.Quad]:
        """What ``live``'s store holds and its files do not, and the reverse:
        read from the store its queries run on."""
        return as_quads(store_lines(live.view.store) ^ self.lines_of(live.base))

    def differ(self, a: LiveKB, changed_a: frozenset[ox.Quad], b: LiveKB, changed_b: frozenset[ox.Quad],
               module: str) -> frozenset[ox.Quad]:
        """The quads of ``module`` one of the stores holds and the other not,
        from each one's :meth:`changed`."""
        return of_module(changed_a ^ changed_b, a, module) ^ self.module_difference(a, b, module)


def written_view(live: LiveKB, module: str) -> frozenset[tuple[Triple, bool]]:
    """What ``module``'s writes make of the view at ``live``: each triple a
    write touched (and each file value a single-valued write competes with),
    and whether it shows.  Cheap enough to take many times a run; two
    holders at the same version must give the same."""
    replica = live.replicas[module]
    touched = set(replica.entries) | replica.removed_base
    seen = replica.visibility.snapshot(touched, live._is_base)
    return frozenset(seen.items())


class WrittenViews:
    """:func:`written_view` of each holder's module, taken again only once
    its replica changed: its version, or the count of its written triples,
    removed file triples or tombstones (a replica changes by a write, a
    delta or a joined state; each adds a dot to its version).  Every change
    at one holder is compared with every other holder at its version, so
    most views asked for are of holders that did not change since."""

    def __init__(self) -> None:
        self._kept: dict[tuple[int, str], tuple[tuple[object, ...], frozenset[tuple[Triple, bool]]]] = {}

    def of(self, live: LiveKB, module: str) -> frozenset[tuple[Triple, bool]]:
        replica = live.replicas[module]
        key = (live.module_version(module), len(replica.entries), len(replica.removed_base), len(replica.tombstones))
        kept = self._kept.get((id(live), module))
        if kept is None or kept[0] != key:
            kept = self._kept[(id(live), module)] = (key, written_view(live, module))
        return kept[1]
