"""The triples a replica's writes added, each with its live dots and their
stamps, and the files' triples its writes removed: the observed-remove set
itself, as data, with no rule about what shows.

Two indexes go with it because the joins need them cheap: from a dot to
its triple (a remove names dots, not triples), and from a subject and a
single-valued predicate to the objects written for it (a single value is
chosen among them, see :mod:`.visibility`).
"""

from __future__ import annotations

from collections.abc import Iterable

from ..model.deltas import Dot, Stamp, WrittenState
from ..model.results import Term, Triple

__all__ = ["WrittenTriples"]


class WrittenTriples:
    """The written triples of one replica (see :mod:`.replica`)."""

    def __init__(self, single_valued: frozenset[Term]) -> None:
        #: The predicates whose objects are indexed by subject.
        self.single_valued = single_valued
        #: Written triple -> its live dots and their stamps (never empty).
        self.entries: dict[Triple, dict[Dot, Stamp]] = {}
        #: The files' triples a write removed: a set that only grows.
        self.removed_base: set[Triple] = set()
        self._by_dot: dict[Dot, Triple] = {}
        #: (subject, single-valued predicate) -> objects with entries
        self._values: dict[tuple[Term, Term], set[Term]] = {}

    def values(self, s: Term, p: Term) -> set[Term]:
        """The written objects of a single-valued property (live or
        shadowed); not to be changed by the caller."""
        return self._values.get((s, p), set())

    def present(self, triple: Triple, is_base: bool) -> bool:
        """Live by the set's rules, before single values shadow any."""
        return bool(self.entries.get(triple)) or (is_base and triple not in self.removed_base)

    def triple_of(self, dot: Dot) -> Triple | None:
        """The live triple ``dot`` tags, if any."""
        return self._by_dot.get(dot)

    def tag(self, triple: Triple, dot: Dot, stamp: Stamp) -> None:
        """``triple`` carries ``dot`` (added under ``stamp``)."""
        self.entries.setdefault(triple, {})[dot] = stamp
        self._by_dot[dot] = triple
        s, p, o = triple
        if p in self.single_valued:
            self._values.setdefault((s, p), set()).add(o)

    def remove_dot(self, dot: Dot) -> bool:
        """Drop ``dot`` from the triple it tags; whether it tagged one."""
        triple = self._by_dot.pop(dot, None)
        if triple is None:
            return False
        self._drop(triple, dot)
        return True

    def removed_in(self, other: WrittenState) -> list[tuple[Triple, Dot]]:
        """The dots here that ``other`` removed: it received them and they
        are gone there, or it knows them removed (a tombstone)."""
        removed = []
        for triple, dots in self.entries.items():
            theirs = other.entries.get(triple, {})
            for dot in dots:
                if (dot in other.context and dot not in theirs) or dot in other.tombstones:
                    removed.append((triple, dot))
        return removed

    def remove(self, removed: Iterable[tuple[Triple, Dot]]) -> None:
        """Drop each dot from its triple."""
        for triple, dot in removed:
            self._drop(triple, dot)
            self._by_dot.pop(dot, None)

    def _drop(self, triple: Triple, dot: Dot) -> None:
        dots = self.entries.get(triple)
        if dots is None:
            return
        dots.pop(dot, None)
        if not dots:
            del self.entries[triple]
            s, p, o = triple
            values = self._values.get((s, p))
            if values is not None:
                values.discard(o)
                if not values:
                    del self._values[(s, p)]
