"""What a local write changes in a replica, worked out before it takes its
dots: the adds that would show anew, and the dots and files' triples its
removes take away.

Kept apart from the replica because of the single values: adding a value
of a single-valued property removes the other values of it this replica
sees (their dots, in the same delta), so the older values do not pile up,
shadowed, write after write; a concurrent value this replica has not seen
survives and loses on its stamp.  Removing a single value removes the
values it shadows too, else an older one would show again.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from ..model.deltas import Dot
from ..model.results import Triple
from .visibility import Visibility

__all__ = ["WritePlan", "plan_write", "unchanged_by"]


@dataclass(frozen=True)
class WritePlan:
    """A local write's delta but for its dots and stamp."""

    added: tuple[Triple, ...]
    removed: tuple[Dot, ...]
    removed_base: tuple[Triple, ...]


def unchanged_by(visibility: Visibility, writer: str, removes: Sequence[Triple], adds: Iterable[Triple],
                 is_base: Callable[[Triple], bool]) -> bool:
    """A write of nothing to remove and only adds that already show under
    ``writer``'s dots changes nothing: no delta, no new version (a retried
    iPATCH keeps the ETag a later If-Match names)."""
    adds = list(adds)
    together = Counter((s, p) for s, p, _ in adds if p in visibility.single_valued)
    return not removes and all(together[t[:2]] <= 1 and visibility.shows_own(writer, t, is_base(t)) for t in adds)


def plan_write(visibility: Visibility, writer: str, removes: Iterable[Triple], adds: Iterable[Triple],
               is_base: Callable[[Triple], bool]) -> WritePlan:
    """Remove what is seen of ``removes``, add ``adds`` (an add that
    already shows under a dot of ``writer``'s is left out: see
    :func:`unchanged_by`)."""
    single_valued, triples = visibility.single_valued, visibility.triples
    named = tuple(dict.fromkeys(adds))
    added = set(named)
    removes = tuple(t for t in dict.fromkeys(removes) if t not in added)
    # Values of one single-valued property written together share a
    # stamp, and show together: none of them is left out.
    together = Counter((s, p) for s, p, _ in named if p in single_valued)
    fresh = tuple(t for t in named if together[t[:2]] > 1 or not visibility.shows_own(writer, t, is_base(t)))
    superseded = [(s, p, o) for s, p, _ in named if p in single_valued
                  for o in triples.values(s, p) if (s, p, o) not in added]
    removed_dots: set[Dot] = set()
    removed_base: dict[Triple, None] = {}
    for triple in removes:
        s, p, _ = triple
        gone = [triple]
        if p in single_valued:
            gone += [(s, p, o) for o in triples.values(s, p)]
            gone += [(s, p, o) for o in visibility.base_values(s, p)]
        for t in gone:
            removed_dots.update(triples.entries.get(t, {}))
            if is_base(t) and t not in triples.removed_base:
                removed_base[t] = None
    for triple in superseded:
        removed_dots.update(triples.entries.get(triple, {}))
    return WritePlan(fresh, tuple(sorted(removed_dots)), tuple(removed_base))
