"""A replicated module's writes as records: the dots that name them, their
hybrid-logical-clock stamps, the causal context of what a replica has seen,
a delta (one write as it travels) and a written state (all of a replica's
writes at once).  Pure data, no I/O: :mod:`coapkb.kb.replica` keeps and
joins them (its docstring describes the model), :mod:`coapkb.wire.sync`
encodes them.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass

from .results import Triple

__all__ = ["BASE_STAMP", "CausalContext", "Delta", "Dot", "MadeUnder", "Stamp", "WrittenState"]


@dataclass(frozen=True, order=True)
class Dot:
    """One write: its writer (a holder's incarnation) and that writer's count."""

    writer: str
    seq: int


@dataclass(frozen=True, order=True)
class Stamp:
    """A hybrid logical clock reading: wall milliseconds, a counter for
    writes within one millisecond or behind a faster clock, and the writer
    (so two stamps are never equal)."""

    ms: int
    counter: int
    writer: str


#: The stamp of a value loaded from the files: older than any write.
BASE_STAMP = Stamp(0, 0, "")


class CausalContext:
    """The dots a replica has seen: a version vector (every seq up to
    ``vv[writer]``) and the dots beyond a gap (``cloud``)."""

    def __init__(self, vv: Mapping[str, int] | None = None, cloud: Iterable[Dot] = ()) -> None:
        self.vv: dict[str, int] = dict(vv or {})
        self.cloud: set[Dot] = set()
        for dot in cloud:
            self.add(dot)

    def __contains__(self, dot: Dot) -> bool:
        return dot.seq <= self.vv.get(dot.writer, 0) or dot in self.cloud

    def __eq__(self, other: object) -> bool:
        return isinstance(other, CausalContext) and self.vv == other.vv and self.cloud == other.cloud

    def __repr__(self) -> str:
        return f"CausalContext({self.vv}, cloud={sorted(self.cloud)})"

    def add(self, dot: Dot) -> None:
        if dot in self:
            return
        if dot.seq == self.vv.get(dot.writer, 0) + 1:
            self.vv[dot.writer] = dot.seq
            self._compact(dot.writer)
        else:
            self.cloud.add(dot)

    def merge(self, other: CausalContext) -> None:
        for writer, seq in other.vv.items():
            if seq > self.vv.get(writer, 0):
                self.vv[writer] = seq
                self._compact(writer)
        for dot in other.cloud:
            self.add(dot)
        self.cloud = {d for d in self.cloud if d.seq > self.vv.get(d.writer, 0)}

    def _compact(self, writer: str) -> None:
        nxt = Dot(writer, self.vv[writer] + 1)
        while nxt in self.cloud:
            self.cloud.discard(nxt)
            self.vv[writer] = nxt.seq
            nxt = Dot(writer, nxt.seq + 1)

    def missing_from(self, other: CausalContext) -> Iterator[Dot]:
        """The dots seen here that ``other`` has not seen."""
        for writer, top in self.vv.items():
            for seq in range(other.vv.get(writer, 0) + 1, top + 1):
                dot = Dot(writer, seq)
                if dot not in other:
                    yield dot
        for dot in self.cloud:
            if dot not in other:
                yield dot

    def count_missing_from(self, other: CausalContext) -> int:
        """How many dots :meth:`missing_from` gives, counted without listing
        the ranges (a context may claim a huge count): each writer's range
        past ``other``'s count, less the dots ``other`` has past its gaps in
        that range, and this context's dots past a gap that ``other`` lacks.
        An upper bound that counted ``other``'s dots past a gap as missing
        sent a whole state where the journal held every missing delta (a
        push overtaken by the next, its dot already compacted away)."""
        behind = sum(max(0, top - other.vv.get(writer, 0)) for writer, top in self.vv.items())
        behind -= sum(1 for dot in other.cloud if dot.seq <= self.vv.get(dot.writer, 0))
        return behind + sum(1 for dot in self.cloud if dot not in other)

    def covers(self, other: CausalContext) -> bool:
        return next(other.missing_from(self), None) is None

    def copy(self) -> CausalContext:
        return CausalContext(self.vv, self.cloud)

    def summary(self) -> tuple[tuple[str, int], ...]:
        """A canonical form (version vector, then the cloud), for a version ETag."""
        return tuple(sorted(self.vv.items())) + tuple((d.writer, -d.seq) for d in sorted(self.cloud))


@dataclass(frozen=True)
class Delta:
    """One write as it travels between holders.

    Its ``i``-th added triple has the dot ``(writer, dot.seq + i)``; a write
    that adds nothing has ``dot`` alone.  ``removed`` are the dots of the
    triples it removed, ``removed_base`` the files' triples it removed."""

    dot: Dot
    stamp: Stamp
    added: tuple[Triple, ...] = ()
    removed: tuple[Dot, ...] = ()
    removed_base: tuple[Triple, ...] = ()

    @property
    def dots(self) -> tuple[Dot, ...]:
        """Every dot the write took."""
        return tuple(Dot(self.dot.writer, self.dot.seq + i) for i in range(max(1, len(self.added))))

    def tagged(self) -> Iterator[tuple[Triple, Dot]]:
        """Its added triples with their dots."""
        for i, triple in enumerate(self.added):
            yield triple, Dot(self.dot.writer, self.dot.seq + i)

    @property
    def size(self) -> int:
        """Triples and dots it carries: what a journal's bound counts."""
        return 1 + len(self.added) + len(self.removed) + len(self.removed_base)


@dataclass(frozen=True)
class MadeUnder:
    """The id a client's write was made under at the holder that pushes its
    delta (docs/knowledge.md, "A write tried again"): another holder a try
    of the write is sent to next answers it as a repeat, not a new write."""

    #: The sender of the write as that holder authenticated it (None: unprotected).
    peer: str | None
    #: The id's parts: its writer, and the write.
    writer: str
    write: str
    #: The digest of the write's method, content-format and body.
    digest: bytes
    #: What the write removed and added, at the holder that made it.
    removed: int
    added: int


@dataclass(frozen=True)
class WrittenState:
    """Everything a replica's writes changed against the files: a whole state
    to join when the journal no longer holds a peer's missing deltas."""

    context: CausalContext
    #: triple -> its live dots and their stamps
    entries: Mapping[Triple, Mapping[Dot, Stamp]]
    removed_base: frozenset[Triple]
    #: Dots removed before their write arrived.
    tombstones: frozenset[Dot] = frozenset()
