"""What a replica's written triples make visible, and what a change did to it.

A triple shows while it carries a dot, or while it is the files' and no
write removed it.  A predicate with one value (a robot's position, its
battery) shows the value whose write has the greatest stamp; the others
stay in the set, shadowed, so the choice is the same everywhere.  The view
queries run on is changed by effects alone (what showed before a change
and not after, and the reverse): the snapshot of a change's triples, and
of the single values competing with them, is taken before and after it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

from ..model.deltas import BASE_STAMP, Stamp
from ..model.results import Term, Triple
from .written_triples import WrittenTriples

__all__ = ["Effect", "Visibility"]


@dataclass(frozen=True)
class Effect:
    """What a delta changed in the visible graph: the store applies it."""

    removed: frozenset[Triple] = frozenset()
    added: frozenset[Triple] = frozenset()

    def __bool__(self) -> bool:
        return bool(self.removed or self.added)


class Visibility:
    """The visible triples of ``triples``.

    ``base_values(s, p)`` gives the files' objects of a single-valued
    property; ``single_valued`` names those properties."""

    def __init__(
        self,
        triples: WrittenTriples,
        single_valued: frozenset[Term],
        base_values: Callable[[Term, Term], Iterable[Term]],
    ) -> None:
        self.triples = triples
        self.single_valued = single_valued
        self.base_values = base_values

    def winners(self, s: Term, p: Term) -> frozenset[Term]:
        """The visible objects of a single-valued property: the greatest stamp's."""
        best: Stamp | None = None
        chosen: set[Term] = set()
        candidates = [(o, True) for o in self.base_values(s, p)] + [(o, False) for o in self.triples.values(s, p)]
        for o, from_base in candidates:
            triple = (s, p, o)
            dots = self.triples.entries.get(triple)
            if dots:
                top = max(dots.values())
            elif from_base and triple not in self.triples.removed_base:
                top = BASE_STAMP
            else:
                continue
            if best is None or top > best:
                best, chosen = top, {o}
            elif top == best:
                chosen.add(o)
        return frozenset(chosen)

    def visible(self, triple: Triple, is_base: bool) -> bool:
        s, p, o = triple
        if p in self.single_valued:
            return o in self.winners(s, p)
        return self.triples.present(triple, is_base)

    def shows_own(self, writer: str, triple: Triple, is_base: bool) -> bool:
        """``triple`` shows, and carries a dot of ``writer``'s (a single
        value shows alone): adding it again (a retried request) would change
        nothing a reader can see."""
        if not any(d.writer == writer for d in self.triples.entries.get(triple, ())):
            return False
        s, p, o = triple
        if p in self.single_valued:
            return self.winners(s, p) == {o} and not self.triples.values(s, p) - {o}
        return self.triples.present(triple, is_base)

    def snapshot(self, triples: Iterable[Triple], is_base: Callable[[Triple], bool]) -> dict[Triple, bool]:
        """Whether each of ``triples`` shows, and each value competing with
        one of them for a single-valued property."""
        seen: dict[Triple, bool] = {}
        judged: dict[tuple[Term, Term], frozenset[Term]] = {}  # each single-valued key's winners, once
        for triple in triples:
            s, p, o = triple
            if p not in self.single_valued:
                seen[triple] = self.triples.present(triple, is_base(triple))
                continue
            winners = judged.get((s, p))
            if winners is None:
                winners = judged[(s, p)] = self.winners(s, p)
                for value in set(self.base_values(s, p)) | self.triples.values(s, p):
                    seen[(s, p, value)] = value in winners
            seen[triple] = o in winners
        return seen

    def effect(self, before: dict[Triple, bool], is_base: Callable[[Triple], bool]) -> Effect:
        """What changed since the snapshot ``before``, on the same triples."""
        after = self.snapshot(before, is_base)
        return Effect(
            removed=frozenset(t for t, v in before.items() if v and not after.get(t, False)),
            added=frozenset(t for t, v in after.items() if v and not before.get(t, False)),
        )
