"""A module's replicated, writable state: a set of triples that every holder
changes and that converges whatever the order of delivery (pure, no I/O).

The model (``docs/knowledge.md``) is a delta-state observed-remove set of
triples, after the ORSWOT of Riak and the delta CRDTs of Almeida et al.:

* Every triple a write adds gets a *dot* ``(writer, seq)`` of its own (a
  write that adds nothing takes one dot too); a writer is one incarnation of
  one holder, and its sequence numbers count up from 1, never taking a dot
  under its name it has already seen (a forged or replayed one).
* A triple is live while it carries at least one dot.  A write that removes
  a triple drops the dots it saw on it.  What the writer did not see (a
  concurrent add) survives: add wins.
* The triples loaded from the module's files carry no dot: they are the
  base every holder loads alike.  Removing one records it in
  ``removed_base``, a set that only grows.
* The *causal context* is the dots of every write a replica has received
  (a version vector plus the dots past a gap).  A delta is a write's dots,
  its adds and the dots it removed.  Applying deltas in any order, twice,
  or a whole state at once gives the same result.  A remove that arrives
  before the add it removes leaves a *tombstone*, the dot alone, until the
  add arrives and is dropped with it.
* A predicate with one value (a robot's position, its battery) keeps the
  value whose write has the greatest hybrid-logical-clock stamp; the
  others stay in the set, shadowed, so the choice is the same everywhere.

Catch-up sends the deltas a peer's context lacks from the journal, so what
it costs grows with what the peer missed; when the journal no longer has
them, the whole written state (what changed against the files, never the
files themselves).
"""

from __future__ import annotations

from collections import Counter, OrderedDict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from ..model.deltas import BASE_STAMP, CausalContext, Delta, Dot, Stamp, WrittenState
from ..model.results import Term, Triple
from ..typed_fields import require_at_least
from .delta_journal import DeltaJournal
from .dot_ledger import DotLedger
from .errors import KBError
from .writer_clock import WriterClock

__all__ = [
    "BASE_STAMP",
    "Effect",
    "Replica",
    "ReplicaFull",
    "ReplicaLimits",
]


@dataclass(frozen=True)
class Effect:
    """What a delta changed in the visible graph: the store applies it."""

    removed: frozenset[Triple] = frozenset()
    added: frozenset[Triple] = frozenset()

    def __bool__(self) -> bool:
        return bool(self.removed or self.added)


@dataclass(frozen=True)
class ReplicaLimits:
    """Bounds on what a write flood can make a replica hold."""

    #: Deltas kept for catch-up, counted in triples and dots (:attr:`Delta.size`);
    #: past it the oldest go and a peer that needs them gets the whole state.
    journal_max: int = 20_000
    #: Written triples (live or shadowed) a replica accepts; past it a local
    #: write is refused (a peer's is still joined: refusing it would split).
    entries_max: int = 100_000
    #: Dots past a gap, waiting for the deltas before them, and tombstones
    #: (dots removed before their write arrived), together.  A delta that
    #: would pass it is not taken: it comes again, in order, at catch-up.
    cloud_max: int = 10_000

    def __post_init__(self) -> None:
        require_at_least(self, ("journal_max", "entries_max", "cloud_max"))


class ReplicaFull(KBError):
    """A local write would pass :attr:`ReplicaLimits.entries_max`."""


class Replica:
    """One holder's copy of a module's writes (see the module docstring).

    ``base_values(s, p)`` gives the files' objects of a single-valued
    property; ``single_valued`` names those properties."""

    def __init__(
        self,
        writer: str,
        *,
        single_valued: frozenset[Term] = frozenset(),
        base_values: Callable[[Term, Term], Iterable[Term]] = lambda s, p: (),
        limits: ReplicaLimits | None = None,
    ) -> None:
        self.writer = writer
        self.single_valued = single_valued
        self._base_values = base_values
        self.limits = limits or ReplicaLimits()
        self.ledger = DotLedger(self.limits.cloud_max)
        self.entries: dict[Triple, dict[Dot, Stamp]] = {}
        self.removed_base: set[Triple] = set()
        self._by_dot: dict[Dot, Triple] = {}
        #: (subject, single-valued predicate) -> objects with entries
        self._values: dict[tuple[Term, Term], set[Term]] = {}
        self._deltas = DeltaJournal(self.limits.journal_max)
        self.clock = WriterClock(writer)
        #: Deltas not taken: they would have passed ``cloud_max``.
        self.refused = 0

    @property
    def context(self) -> CausalContext:
        """The dots of every write received."""
        return self.ledger.context

    @property
    def tombstones(self) -> set[Dot]:
        """Dots removed before their write came."""
        return self.ledger.tombstones

    def stamp(self, now_ms: int) -> Stamp:
        """The next hybrid-logical-clock stamp of a local write."""
        return self.clock.stamp(now_ms)

    # ---------------------------------------------------------- visibility

    def shows_own(self, triple: Triple, is_base: bool) -> bool:
        """``triple`` shows, and carries a dot of this writer's (a single
        value shows alone): adding it again (a retried request) would change
        nothing a reader can see."""
        if not any(d.writer == self.writer for d in self.entries.get(triple, ())):
            return False
        s, p, o = triple
        if p in self.single_valued:
            return self._winners(s, p) == {o} and not self._values.get((s, p), set()) - {o}
        return self._present(triple, is_base)

    def unchanged_by(self, removes: Sequence[Triple], adds: Iterable[Triple], is_base: Callable[[Triple], bool]) -> bool:
        """A write of nothing to remove and only adds that already show under
        this writer's dots changes nothing: no delta, no new version (a
        retried iPATCH keeps the ETag a later If-Match names)."""
        adds = list(adds)
        together = Counter((s, p) for s, p, _ in adds if p in self.single_valued)
        return not removes and all(together[t[:2]] <= 1 and self.shows_own(t, is_base(t)) for t in adds)

    def _present(self, triple: Triple, is_base: bool) -> bool:
        """Live by the set's rules, before single values shadow any."""
        return bool(self.entries.get(triple)) or (is_base and triple not in self.removed_base)

    def _winners(self, s: Term, p: Term) -> frozenset[Term]:
        """The visible objects of a single-valued property: the greatest stamp's."""
        best: Stamp | None = None
        chosen: set[Term] = set()
        candidates = [(o, True) for o in self._base_values(s, p)] + [(o, False) for o in self._values.get((s, p), ())]
        for o, from_base in candidates:
            triple = (s, p, o)
            dots = self.entries.get(triple)
            if dots:
                top = max(dots.values())
            elif from_base and triple not in self.removed_base:
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
            return o in self._winners(s, p)
        return self._present(triple, is_base)

    def _snapshot(self, triples: Iterable[Triple], is_base: Callable[[Triple], bool]) -> dict[Triple, bool]:
        seen: dict[Triple, bool] = {}
        for triple in triples:
            s, p, _ = triple
            if p in self.single_valued:
                winners = self._winners(s, p)
                for o in set(self._base_values(s, p)) | self._values.get((s, p), set()):
                    seen[(s, p, o)] = o in winners
            seen[triple] = self.visible(triple, is_base(triple))
        return seen

    def _effect(self, before: dict[Triple, bool], is_base: Callable[[Triple], bool]) -> Effect:
        after = self._snapshot(before, is_base)
        return Effect(
            removed=frozenset(t for t, v in before.items() if v and not after.get(t, False)),
            added=frozenset(t for t, v in after.items() if v and not before.get(t, False)),
        )

    # --------------------------------------------------------------- writes

    def write(
        self, removes: Iterable[Triple], adds: Iterable[Triple], now_ms: int, is_base: Callable[[Triple], bool]
    ) -> tuple[Delta, Effect]:
        """A local write: remove what is seen of ``removes``, add ``adds``
        (an add that already shows under a dot of this writer's is left out:
        see :meth:`unchanged_by`).

        Adding a value of a single-valued property removes the other values
        of it this replica sees (their dots, in the same delta): the older
        values do not pile up, shadowed, write after write.  A concurrent
        value this replica has not seen survives and loses on its stamp.

        Raises :class:`ReplicaFull` past the entries bound (nothing changes)."""
        named = tuple(dict.fromkeys(adds))
        added = set(named)
        removes = tuple(t for t in dict.fromkeys(removes) if t not in added)
        # Values of one single-valued property written together share a
        # stamp, and show together: none of them is left out.
        together = Counter((s, p) for s, p, _ in named if p in self.single_valued)
        adds = tuple(t for t in named if together[t[:2]] > 1 or not self.shows_own(t, is_base(t)))
        superseded = [(s, p, o) for s, p, _ in named if p in self.single_valued
                      for o in self._values.get((s, p), ()) if (s, p, o) not in added]
        fresh = sum(1 for t in adds if t not in self.entries)
        if len(self.entries) + fresh > self.limits.entries_max:
            raise ReplicaFull(
                f"this module holds {len(self.entries)} written triples; at most {self.limits.entries_max}"
            )
        removed_dots: set[Dot] = set()
        removed_base: dict[Triple, None] = {}
        for triple in removes:
            s, p, _ = triple
            # Removing a single value removes the values it shadows too:
            # else an older one would show again.
            gone = [triple]
            if p in self.single_valued:
                gone += [(s, p, o) for o in self._values.get((s, p), ())]
                gone += [(s, p, o) for o in self._base_values(s, p)]
            for t in gone:
                removed_dots.update(self.entries.get(t, {}))
                if is_base(t) and t not in self.removed_base:
                    removed_base[t] = None
        for triple in superseded:
            removed_dots.update(self.entries.get(triple, {}))
        first = Dot(self.writer, self.clock.first_seq(max(1, len(adds)), self.ledger))
        delta = Delta(first, self.stamp(now_ms), adds, tuple(sorted(removed_dots)), tuple(removed_base))
        self.clock.took(delta.dots[-1])
        return delta, self.apply(delta, is_base)

    def apply(self, delta: Delta, is_base: Callable[[Triple], bool]) -> Effect:
        """Join a delta (idempotent, in any order); what it changed in view."""
        if delta.dot in self._deltas:
            return Effect()  # a duplicate
        received = delta.dot in self.context
        if not self.ledger.admits(delta):
            self.refused += 1
            return Effect()
        self.clock.observe(delta.stamp)
        touched: set[Triple] = set(delta.added) | set(delta.removed_base)
        touched |= {self._by_dot[d] for d in delta.removed if d in self._by_dot}
        before = self._snapshot(touched, is_base)
        for dot in delta.removed:
            triple = self._by_dot.pop(dot, None)
            if triple is not None:
                self._drop(triple, dot)
            else:
                self.ledger.bury(dot)  # removed before its write came: it never shows
        if not received:
            for triple, dot in delta.tagged():
                if not self.ledger.buried(dot):
                    self._tag(triple, dot, delta.stamp)
            self.ledger.receive(delta.dots)
        self.removed_base.update(delta.removed_base)
        self._deltas.add(delta)
        return self._effect(before, is_base)

    def _tag(self, triple: Triple, dot: Dot, stamp: Stamp) -> None:
        self.entries.setdefault(triple, {})[dot] = stamp
        self._by_dot[dot] = triple
        s, p, o = triple
        if p in self.single_valued:
            self._values.setdefault((s, p), set()).add(o)

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

    # ---------------------------------------------------------- the journal

    @property
    def journal(self) -> OrderedDict[Dot, Delta]:
        """The deltas kept for catch-up, by first dot, oldest first."""
        return self._deltas.deltas

    @property
    def journal_size(self) -> int:
        return self._deltas.size

    def compact(self, peers: Iterable[CausalContext]) -> int:
        """Forget the deltas every peer in ``peers`` has received; how many went."""
        return self._deltas.compact(peers)

    def missing_for(self, peer: CausalContext) -> list[Delta] | WrittenState:
        """What ``peer`` lacks: the deltas from the journal, in the order
        they came, or the whole written state when the journal no longer
        holds one of them."""
        deltas = self._deltas.missing_from(self.context, peer)
        return self.state() if deltas is None else deltas

    # ---------------------------------------------------------- whole state

    def state(self) -> WrittenState:
        return WrittenState(
            self.context.copy(),
            {t: dict(dots) for t, dots in self.entries.items()},
            frozenset(self.removed_base),
            frozenset(self.tombstones),
        )

    def join(self, other: WrittenState, is_base: Callable[[Triple], bool]) -> Effect:
        """Join a whole state (a peer's, for catch-up)."""
        touched: set[Triple] = set(other.entries) | (set(other.removed_base) - self.removed_base)
        removed: list[tuple[Triple, Dot]] = []
        for triple, dots in self.entries.items():
            theirs = other.entries.get(triple, {})
            for dot in dots:
                # They received it and it is gone there, or they know it removed.
                if (dot in other.context and dot not in theirs) or dot in other.tombstones:
                    removed.append((triple, dot))
                    touched.add(triple)
        before = self._snapshot(touched, is_base)
        for triple, dot in removed:
            self._drop(triple, dot)
            self._by_dot.pop(dot, None)
        for triple, theirs in other.entries.items():
            for dot, stamp in theirs.items():
                self.clock.observe(stamp)
                if not self.ledger.knows(dot):
                    self._tag(triple, dot, stamp)
        self.removed_base |= other.removed_base
        self.ledger.merge(other.context, other.tombstones)
        return self._effect(before, is_base)

    def equal_to(self, other: Replica) -> bool:
        """Same set, same context (for tests and the simulator's checker)."""
        return (
            self.context == other.context
            and self.entries == other.entries
            and self.removed_base == other.removed_base
            and self.tombstones == other.tombstones
        )

    def gaps(self) -> int:
        """Dots waiting: past a gap, or removed before their write came."""
        return self.ledger.waiting()

