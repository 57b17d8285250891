"""How long a restarted holder takes to catch up, watched from outside it.

A holder that starts again (no data folder: empty of writes; with one: as
its journal left it) must learn what its co-holders acknowledged meanwhile.
Every end state may agree and still hide a catch-up that never runs at the
start: the periodic anti-entropy would mend it 3-7 s later, while the
holder answers its teammates' queries without those writes.  So the
simulator times it: at the restart it notes the acknowledged values every
other running holder of each module shows, and the moment the new process
shows them all (or they were deleted since) is one sample.  The profile's
median is judged by :func:`coapkb.sim.invariants.check_catch_up`.

The reads a holder answers meanwhile are watched too (:meth:`CatchUps.answered`,
a hook on the simulated network's answers and notifications): a query
answered, or an answer pushed on ``/kb/facts``, by a holder that still owes
acknowledged values of the module it reads is a read its co-holders would
have answered with them.  The same oracle judges them: there should be none.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

from ..kb.live import LiveKB
from ..kb.named_queries import NAMED_QUERIES
from ..transport.messages import Request, Response
from .loop import Process

#: The paths a holder answers queries on, and pushes its answers on (notifications).
_READS = ("/kb/q/", "/kb/sparql", "/kb/facts/")

def _modules_read(path: str) -> frozenset[str] | None:
    """The KB modules a read on ``path`` answers from (None: any, SPARQL text)."""
    if path.startswith("/kb/q/"):
        query = NAMED_QUERIES.get(path.removeprefix("/kb/q/"))
        return None if query is None else frozenset({query.kb})
    if path.startswith("/kb/facts/"):
        return frozenset({path.removeprefix("/kb/facts/")})
    return None


#: Whether a holder's KB shows a written value: (kb, module, value).
Shows = Callable[[LiveKB, str, int], bool]


class CatchUps:
    """The catch-ups of one run: those begun, and how long each one took."""

    def __init__(self, clock: Callable[[], float], shows: Shows) -> None:
        self._clock = clock
        self._shows = shows
        #: Robot -> (when its process restarted, module -> values it still lacks).
        self._pending: dict[str, tuple[float, dict[str, set[int]]]] = {}
        #: Values a delete was sent for: no longer owed.
        self._deleted: set[tuple[str, int]] = set()
        #: Simulated seconds from each restart to its holder's having caught up.
        self.took_s: list[float] = []
        #: Queries answered by a holder that still owed values, one line each.
        self.stale_reads: list[str] = []

    def expect(self, robot_id: str, owed: Mapping[str, set[int]]) -> None:
        """``robot_id`` restarts now and owes ``owed`` (module -> values)."""
        owed = {m: set(v) for m, v in owed.items() if v}
        if owed:
            self._pending[robot_id] = (self._clock(), owed)
        else:
            self._pending.pop(robot_id, None)

    def deleting(self, module: str, value: int) -> None:
        self._deleted.add((module, value))

    def killed(self, robot_id: str) -> None:
        """A process killed before it caught up: no sample (its catch-up was cut short)."""
        self._pending.pop(robot_id, None)

    def changed(self, robot_id: str, kb: LiveKB) -> None:
        """``robot_id``'s current process's KB changed (or started): caught up yet?"""
        entry = self._pending.get(robot_id)
        if entry is None:
            return
        since, owed = entry
        for module, values in owed.items():
            values -= {v for v in values if (module, v) in self._deleted or self._shows(kb, module, v)}
        if not any(owed.values()):
            del self._pending[robot_id]
            self.took_s.append(round(self._clock() - since, 6))

    def answered(self, server: Process, request: Request, response: Response) -> None:
        """A hook on the network's answers: a query ``server`` answered
        while its process still owed values of a module the query reads is
        a stale read."""
        entry = self._pending.get(server.name)
        if entry is None or not response.status.is_success or not request.path.startswith(_READS):
            return
        since, owed = entry
        read = _modules_read(request.path)
        lacking = ", ".join(f"{len(values)} of {module}" for module, values in sorted(owed.items())
                            if values and (read is None or module in read))
        if lacking:
            self.stale_reads.append(
                f"{server.name} answered {request.method.name} {request.path} {self._clock() - since:.3f} s after "
                f"its restart, still lacking acknowledged values ({lacking})")

    def finish(self) -> list[float]:
        """Every sample: a catch-up unfinished at the end counts until now (at least that long)."""
        now = self._clock()
        self.took_s += [round(now - since, 6) for since, _ in self._pending.values()]
        self._pending.clear()
        return list(self.took_s)
