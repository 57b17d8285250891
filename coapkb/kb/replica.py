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

:class:`Replica` joins the parts each of its own module keeps:

* :mod:`.written_triples`: the triples and their dots, the files' triples removed;
* :mod:`.dot_ledger`: the causal context and the tombstones, and their bound;
* :mod:`.visibility`: what shows (single values shadowed) and a change's effect;
* :mod:`.write_plan`: what a local write removes and adds;
* :mod:`.writer_clock`: the dots and stamps of this writer's own writes;
* :mod:`.delta_journal`: the deltas kept for catch-up.
"""

from __future__ import annotations

import dataclasses
from collections import OrderedDict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from ..model.deltas import BASE_STAMP, CausalContext, Delta, Dot, Stamp, WrittenState
from ..model.results import Term, Triple
from ..typed_fields import require_at_least
from .delta_journal import DeltaJournal
from .dot_ledger import DotLedger
from .errors import KBError
from .visibility import Effect, Visibility
from .write_plan import plan_write, unchanged_by
from .writer_clock import WriterClock
from .written_triples import WrittenTriples

__all__ = [
    "BASE_STAMP",
    "Effect",
    "Replica",
    "ReplicaFull",
    "ReplicaLimits",
]


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
        self.limits = limits or ReplicaLimits()
        self.triples = WrittenTriples(single_valued)
        self.ledger = DotLedger(self.limits.cloud_max)
        self.visibility = Visibility(self.triples, single_valued, base_values)
        self.clock = WriterClock(writer)
        self._deltas = DeltaJournal(self.limits.journal_max)
        #: Deltas not taken: they would have passed ``cloud_max``.
        self.refused = 0

    # The parts' records, under the names the rest of the package reads.

    @property
    def context(self) -> CausalContext:
        """The dots of every write received."""
        return self.ledger.context

    @property
    def tombstones(self) -> set[Dot]:
        """Dots removed before their write came."""
        return self.ledger.tombstones

    @property
    def entries(self) -> dict[Triple, dict[Dot, Stamp]]:
        """Written triple -> its live dots and their stamps."""
        return self.triples.entries

    @property
    def removed_base(self) -> set[Triple]:
        """The files' triples a write removed."""
        return self.triples.removed_base

    @property
    def journal(self) -> OrderedDict[Dot, Delta]:
        """The deltas kept for catch-up, by first dot, oldest first."""
        return self._deltas.deltas

    @property
    def journal_size(self) -> int:
        return self._deltas.size

    def stamp(self, now_ms: int) -> Stamp:
        """The next hybrid-logical-clock stamp of a local write."""
        return self.clock.stamp(now_ms)

    def visible(self, triple: Triple, is_base: bool) -> bool:
        return self.visibility.visible(triple, is_base)

    def shows_own(self, triple: Triple, is_base: bool) -> bool:
        """``triple`` shows under a dot of this writer's (:meth:`Visibility.shows_own`)."""
        return self.visibility.shows_own(self.writer, triple, is_base)

    def unchanged_by(self, removes: Sequence[Triple], adds: Iterable[Triple], is_base: Callable[[Triple], bool]) -> bool:
        """A write that would change nothing (:func:`.write_plan.unchanged_by`)."""
        return unchanged_by(self.visibility, self.writer, removes, adds, is_base)

    def bound_waiting(self, waiting_max: int) -> None:
        """Another bound on the waiting dots (:attr:`ReplicaLimits.cloud_max`),
        from now on (the simulator's small bound)."""
        self.limits = dataclasses.replace(self.limits, cloud_max=waiting_max)
        self.ledger.waiting_max = waiting_max

    def gaps(self) -> int:
        """Dots waiting: past a gap, or removed before their write came."""
        return self.ledger.waiting()

    # --------------------------------------------------------------- writes

    def write(
        self, removes: Iterable[Triple], adds: Iterable[Triple], now_ms: int, is_base: Callable[[Triple], bool]
    ) -> tuple[Delta, Effect]:
        """A local write (:func:`.write_plan.plan_write`), joined here.

        Raises :class:`ReplicaFull` past the entries bound (nothing changes)."""
        plan = plan_write(self.visibility, self.writer, removes, adds, is_base)
        fresh = sum(1 for t in plan.added if t not in self.entries)
        if len(self.entries) + fresh > self.limits.entries_max:
            raise ReplicaFull(
                f"this module holds {len(self.entries)} written triples; at most {self.limits.entries_max}"
            )
        first = Dot(self.writer, self.clock.first_seq(max(1, len(plan.added)), self.ledger))
        delta = Delta(first, self.stamp(now_ms), plan.added, plan.removed, plan.removed_base)
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
        touched |= {t for d in delta.removed if (t := self.triples.triple_of(d)) is not None}
        before = self.visibility.snapshot(touched, is_base)
        for dot in delta.removed:
            if not self.triples.remove_dot(dot):
                self.ledger.bury(dot)  # removed before its write came: it never shows
        if not received:
            for triple, dot in delta.tagged():
                if not self.ledger.buried(dot):
                    self.triples.tag(triple, dot, delta.stamp)
            self.ledger.receive(delta.dots)
        self.removed_base.update(delta.removed_base)
        self._deltas.add(delta)
        return self.visibility.effect(before, is_base)

    # --------------------------------------------------------------- lives

    @property
    def has_written(self) -> bool:
        """A dot under this replica's writer is known: it took one, or one came."""
        return bool(self.clock.seq) or self.ledger.highest(self.writer) > 0

    def continue_as(self, writer: str) -> None:
        """Write from now on as ``writer``, the name of this robot's lives,
        above every dot of it known here (:mod:`.life_fence` says when that
        is safe).

        Raises :class:`ValueError` once this replica's writer has a dot."""
        if self.has_written:
            raise ValueError(f"{self.writer} has written: it cannot write as {writer}")
        self.writer = writer
        self.clock.continue_as(writer)

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
        removed = self.triples.removed_in(other)
        touched.update(triple for triple, _ in removed)
        before = self.visibility.snapshot(touched, is_base)
        self.triples.remove(removed)
        for triple, theirs in other.entries.items():
            for dot, stamp in theirs.items():
                self.clock.observe(stamp)
                if not self.ledger.knows(dot):
                    self.triples.tag(triple, dot, stamp)
        self.removed_base.update(other.removed_base)
        self.ledger.merge(other.context, other.tombstones)
        return self.visibility.effect(before, is_base)

    def equal_to(self, other: Replica) -> bool:
        """Same set, same context (for tests and the simulator's checker)."""
        return (
            self.context == other.context
            and self.entries == other.entries
            and self.removed_base == other.removed_base
            and self.tombstones == other.tombstones
        )

    # ---------------------------------------------------------- the journal

    def compact(self, peers: Iterable[CausalContext]) -> int:
        """Forget the deltas every peer in ``peers`` has received; how many went."""
        return self._deltas.compact(peers)

    def missing_for(self, peer: CausalContext) -> list[Delta] | WrittenState:
        """What ``peer`` lacks: the deltas from the journal, in the order
        they came, or the whole written state when the journal no longer
        holds one of them."""
        deltas = self._deltas.missing_from(self.context, peer)
        return self.state() if deltas is None else deltas
