"""The replicated set of a module's triples (coapkb/kb/replica.py), pure.

* Convergence: three writers make random local writes while deltas travel
  between them, twice or not yet, with whole-state joins and journal
  catch-ups mixed in; once everything reached everyone, every replica holds
  the same state and shows the same graph, whether deltas arrive in causal
  order or in any order.
* A local write removes and adds what it names, nothing else.
* Add wins over a concurrent remove; a remove that arrives before its add
  still removes; a single-valued predicate keeps the greatest stamp.
* The journal hands a peer the deltas it missed, or the whole written state
  once it no longer has them; the entries bound refuses a local write whole.
* A causal context is a version vector plus a compacted cloud of dots.
"""

from __future__ import annotations

import random
from collections.abc import Callable, Sequence
from typing import NamedTuple

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from rdflib.term import Literal, URIRef

from coapkb.kb.replica import BASE_STAMP, Effect, Replica, ReplicaFull, ReplicaLimits
from coapkb.model.deltas import CausalContext, Delta, Dot, Stamp, WrittenState
from coapkb.model.results import Term, Triple

EX = "http://example.org/team#"
LOC = "http://www.tcs.org/2018/Location#"

ROBOT1, ROBOT2 = URIRef(EX + "Robot1"), URIRef(EX + "Robot2")
NEAR, HOLDS = URIRef(EX + "near"), URIRef(EX + "holds")
#: One single-valued predicate (as in coapkb.world.vocabulary.SINGLE_VALUED).
AISLE = URIRef(LOC + "Robot_aisle_no")
SINGLE = frozenset({AISLE})
THINGS = (URIRef(EX + "shelf_a"), URIRef(EX + "shelf_b"), Literal("crate"))
AISLES = (Literal(1), Literal(2), Literal(3))

#: Every triple a program can touch: small, so writes collide often.
UNIVERSE: tuple[Triple, ...] = tuple(
    (s, p, o) for s in (ROBOT1, ROBOT2) for p in (NEAR, HOLDS) for o in THINGS
) + tuple((s, AISLE, o) for s in (ROBOT1, ROBOT2) for o in AISLES)
#: The files' triples: no dot, the same on every holder (one single value among them).
BASE: frozenset[Triple] = frozenset({(ROBOT1, NEAR, THINGS[0]), (ROBOT2, HOLDS, THINGS[2]), (ROBOT1, AISLE, AISLES[0])})
WRITERS = ("A.1", "B.1", "C.1")
#: Two written triples that are not in the files, and one that is.
X: Triple = (ROBOT2, NEAR, THINGS[1])
Y: Triple = (ROBOT2, HOLDS, THINGS[0])
FILE_TRIPLE: Triple = (ROBOT1, NEAR, THINGS[0])
_X, _Y, _T = UNIVERSE.index(X), UNIVERSE.index(Y), UNIVERSE.index(FILE_TRIPLE)


def replica(writer: str, base: frozenset[Triple] = BASE, limits: ReplicaLimits | None = None) -> Replica:
    def base_values(s: Term, p: Term) -> list[Term]:
        return [o for (bs, bp, o) in sorted(base) if bs == s and bp == p]

    return Replica(writer, single_valued=SINGLE, base_values=base_values, limits=limits)


def is_base_of(base: frozenset[Triple]) -> Callable[[Triple], bool]:
    return lambda t: t in base


is_base = is_base_of(BASE)


def visible(r: Replica, base: frozenset[Triple] = BASE) -> frozenset[Triple]:
    """The graph a replica shows, over the universe."""
    return frozenset(t for t in UNIVERSE if r.visible(t, t in base))


def values(r: Replica, s: Term, p: Term = AISLE, base: frozenset[Triple] = BASE) -> set[Term]:
    """The visible objects of (s, p), the universe's or any other a test wrote."""
    candidates = {t for t in (*UNIVERSE, *r.entries, *base) if t[0] == s and t[1] == p}
    return {t[2] for t in candidates if r.visible(t, t in base)}


def check_invariants(r: Replica) -> None:
    # Every live dot has been seen, the cloud holds only dots past a gap,
    # and the journal's size is what its deltas carry.
    for dots in r.entries.values():
        assert dots and all(d in r.context for d in dots)
    for d in r.context.cloud:
        assert d.seq > r.context.vv.get(d.writer, 0) + 1, r.context
    assert r.journal_size == sum(d.size for d in r.journal.values())


# --------------------------------------------------------------------------- random programs


class Write(NamedTuple):
    at: int  # which replica writes
    removes: tuple[int, ...]  # universe indices; one not visible there picks a visible one
    adds: tuple[int, ...]
    ms: int  # the writer's wall clock: not monotonic, the HLC copes


class Deliver(NamedTuple):
    pick: int  # a delta written so far (modulo their number): duplicates happen
    to: int


class Join(NamedTuple):
    source: int
    to: int


class CatchUp(NamedTuple):
    source: int
    to: int


Step = Write | Deliver | Join | CatchUp

_index = st.integers(0, len(UNIVERSE) - 1)
_who = st.integers(0, len(WRITERS) - 1)
STEPS = st.one_of(
    st.builds(Write, _who, st.tuples(_index) | st.tuples(_index, _index) | st.just(()),
              st.lists(_index, max_size=3).map(tuple), st.integers(0, 30)),
    st.builds(Deliver, st.integers(0, 1000), _who),
    st.builds(Deliver, st.integers(0, 1000), _who),
    st.builds(Join, _who, _who),
    st.builds(CatchUp, _who, _who),
)


def chosen_removes(r: Replica, picks: Sequence[int], base: frozenset[Triple]) -> list[Triple]:
    """Removes from what the writer sees (a robot deletes what it reads):
    the universe's triple if visible, else a visible one."""
    seen = sorted(visible(r, base), key=UNIVERSE.index)
    if not seen:
        return []
    return [UNIVERSE[i] if UNIVERSE[i] in seen else seen[i % len(seen)] for i in picks]


class Team:
    """Three replicas and every delta written, with what its writer had seen."""

    def __init__(self, base: frozenset[Triple], causal: bool) -> None:
        self.base, self.causal = base, causal
        self.is_base = is_base_of(base)
        self.replicas = [replica(w, base) for w in WRITERS]
        self.sent: list[tuple[Delta, CausalContext]] = []

    def deliverable(self, to: Replica, deps: CausalContext) -> bool:
        # Causal delivery: only once the receiver saw what the writer had seen.
        return not self.causal or to.context.covers(deps)

    def run(self, step: Step) -> None:
        rs = self.replicas
        if isinstance(step, Write):
            r = rs[step.at]
            deps = r.context.copy()
            removes, adds = chosen_removes(r, step.removes, self.base), [UNIVERSE[i] for i in step.adds]
            delta, _ = r.write(removes, adds, step.ms, self.is_base)
            assert delta.stamp > max((d.stamp for d, _ in self.sent if d.dot.writer == r.writer), default=BASE_STAMP)
            self.sent.append((delta, deps))
        elif isinstance(step, Deliver):
            if self.sent:
                delta, deps = self.sent[step.pick % len(self.sent)]
                if self.deliverable(rs[step.to], deps):
                    rs[step.to].apply(delta, self.is_base)
        elif isinstance(step, Join):
            rs[step.to].join(rs[step.source].state(), self.is_base)
        else:
            self.catch_up(rs[step.source], rs[step.to])
        for r in rs:
            check_invariants(r)

    def catch_up(self, source: Replica, to: Replica) -> None:
        changes = source.missing_for(to.context)
        if isinstance(changes, WrittenState):
            to.join(changes, self.is_base)
        else:
            for delta in changes:
                to.apply(delta, self.is_base)
        assert to.context.covers(source.context)

    def deliver_everything(self, seed: int) -> None:
        rng = random.Random(seed)
        for r in self.replicas:
            pending = self.sent * 2  # twice: the second time changes nothing
            rng.shuffle(pending)
            while pending:
                ready = [p for p in pending if self.deliverable(r, p[1])]
                assert ready, "a delta waits on a dot no delta carries"
                for delta, _deps in ready:
                    r.apply(delta, self.is_base)
                pending = [p for p in pending if all(p is not q for q in ready)]


# The smallest programs that lost a removal before deltas carried their own
# removals even when their dot was already known (found by the property test).
# A removes a file triple and adds x; B sees that and removes x; C gets B's
# delta before A's, and never records the file triple as removed.
LOST_BASE_REMOVAL = [Write(0, (_T,), (_X,), 1), Deliver(0, 1), Write(1, (_X,), (), 2), Deliver(1, 2)]
# A adds x, replaces it by y, removes y; B gets the first, the third, then the
# second, whose removal of x it never makes.
LOST_REMOVAL = [Write(0, (), (_X,), 1), Write(0, (_X,), (_Y,), 2), Write(0, (_Y,), (), 3),
                Deliver(0, 1), Deliver(2, 1), Deliver(1, 1)]


@pytest.mark.parametrize(
    "causal",
    [
        pytest.param(True, id="causal-delivery"),
        pytest.param(False, id="any-order"),
    ],
)
@settings(max_examples=200, deadline=None)
@given(program=st.lists(STEPS, max_size=30), seed=st.integers(0, 2**16))
@example(program=LOST_BASE_REMOVAL, seed=0)
@example(program=LOST_REMOVAL, seed=0)
def test_replicas_converge_whatever_the_delivery(causal: bool, program: list[Step], seed: int) -> None:
    team = Team(BASE, causal)
    for step in program:
        team.run(step)
    team.deliver_everything(seed)
    a, *others = team.replicas
    for other in others:
        assert a.equal_to(other), (a.state(), other.state())
        assert visible(a) == visible(other)
        assert a.missing_for(other.context) == []


def test_a_delta_that_comes_after_the_removal_of_its_add_still_removes() -> None:
    a, b = replica("A.1"), replica("B.1")
    add, _ = a.write([], [X], 1, is_base)
    replace, _ = a.write([X], [Y], 2, is_base)
    remove, _ = a.write([Y], [], 3, is_base)
    for delta in (add, remove, replace):  # the second one late
        b.apply(delta, is_base)
    assert a.missing_for(b.context) == []  # so no catch-up would ever repair B
    assert not b.visible(X, False) and b.equal_to(a)


def test_a_file_triple_removal_that_comes_late_still_removes() -> None:
    a, b, c = replica("A.1"), replica("B.1"), replica("C.1")
    first, _ = a.write([FILE_TRIPLE], [X], 1, is_base)
    b.apply(first, is_base)
    second, _ = b.write([X], [], 2, is_base)
    c.apply(second, is_base)
    c.apply(first, is_base)
    assert not c.visible(FILE_TRIPLE, True) and c.equal_to(b)


# --------------------------------------------------------------------------- local writes

def write_semantics(writes: Sequence[tuple[tuple[int, ...], tuple[int, ...], int]]) -> None:
    """One replica's writes, each checked against what it named."""
    r = replica("A.1")
    for remove_idx, add_idx, ms in writes:
        before = visible(r)
        removes = set(chosen_removes(r, remove_idx, BASE))
        adds = {UNIVERSE[i] for i in add_idx}
        r.write(sorted(removes, key=UNIVERSE.index), sorted(adds, key=UNIVERSE.index), ms, is_base)
        after = visible(r)
        plain = {t for t in UNIVERSE if t[1] not in SINGLE}
        assert after & plain == ((before - removes) | adds) & plain
        for s in (ROBOT1, ROBOT2):
            added = {o for (ts, tp, o) in adds if ts == s and tp == AISLE}
            if added:  # the newest stamp wins
                assert values(r, s) == added
            elif any(ts == s and tp == AISLE for (ts, tp, _) in removes - adds):
                assert values(r, s) == set()  # shadowed values go with the winner
            else:
                assert values(r, s) == {o for (ts, tp, o) in before if ts == s and tp == AISLE}
        check_invariants(r)


WriteOps = list[tuple[tuple[int, ...], tuple[int, ...], int]]
_write_ops = st.tuples(st.lists(_index, max_size=2).map(tuple), st.lists(_index, max_size=1).map(tuple),
                       st.integers(0, 30))


@settings(max_examples=150, deadline=None)
@given(writes=st.lists(_write_ops, max_size=12))
def test_a_local_write_of_one_triple_does_what_it_names(writes: WriteOps) -> None:
    write_semantics(writes)


@settings(max_examples=150, deadline=None)
@given(writes=st.lists(st.tuples(st.lists(_index, max_size=2).map(tuple), st.lists(_index, max_size=3).map(tuple),
                                 st.integers(0, 30)), max_size=12))
@example(writes=[((), (_X, _Y), 1), ((_X,), (), 2)])
def test_a_local_write_of_several_triples_does_what_it_names(writes: WriteOps) -> None:
    write_semantics(writes)


def test_removing_one_triple_of_a_write_keeps_the_others() -> None:
    a = replica("A.1")
    a.write([], [X, Y], 1, is_base)
    _, effect = a.write([X], [], 2, is_base)
    assert effect == Effect(removed=frozenset({X}))
    assert a.visible(Y, False)


def test_a_write_reports_its_effect_and_a_duplicate_changes_nothing() -> None:
    a, b = replica("A.1"), replica("B.1")
    delta, effect = a.write([], [X], 1, is_base)
    assert effect == Effect(added=frozenset({X})) and delta.dot == Dot("A.1", 1)
    assert b.apply(delta, is_base) == Effect(added=frozenset({X}))
    assert not b.apply(delta, is_base)  # idempotent
    assert a.equal_to(b)


# --------------------------------------------------------------------------- add wins, remove first


def test_add_wins_over_a_concurrent_remove() -> None:
    a, b, c = replica("A.1"), replica("B.1"), replica("C.1")
    first, _ = a.write([], [X], 1, is_base)
    b.apply(first, is_base)
    # A removes x while B, not having seen that, adds it again.
    removal, _ = a.write([X], [], 2, is_base)
    re_add, _ = b.write([], [X], 3, is_base)
    for r, deltas in ((a, [re_add]), (b, [removal]), (c, [re_add, removal, first])):
        for d in deltas:
            r.apply(d, is_base)
    assert all(r.visible(X, False) for r in (a, b, c))
    assert a.equal_to(b) and b.equal_to(c)


def test_add_wins_over_a_concurrent_remove_of_a_file_triple() -> None:
    base_triple = FILE_TRIPLE
    a, b = replica("A.1"), replica("B.1")
    removal, _ = a.write([base_triple], [], 1, is_base)
    add, _ = b.write([], [base_triple], 2, is_base)
    assert removal.removed_base == (base_triple,)
    a.apply(add, is_base)
    b.apply(removal, is_base)
    assert a.visible(base_triple, True) and b.visible(base_triple, True) and a.equal_to(b)


def test_a_remove_delivered_before_its_add_still_removes() -> None:
    a, b, c = replica("A.1"), replica("B.1"), replica("C.1")
    add, _ = a.write([], [X], 1, is_base)
    b.apply(add, is_base)
    remove, _ = b.write([X], [], 2, is_base)
    assert remove.removed == (add.dot,)
    assert c.apply(remove, is_base) == Effect()
    assert c.apply(add, is_base) == Effect()  # its dot is already removed: nothing shows
    assert not c.visible(X, False)
    a.apply(remove, is_base)
    assert a.equal_to(b) and b.equal_to(c)


# --------------------------------------------------------------------------- single values


def test_concurrent_single_values_converge_to_the_greatest_stamp() -> None:
    a, b, c = replica("A.1"), replica("B.1"), replica("C.1")
    five, six = (ROBOT1, AISLE, Literal(5)), (ROBOT1, AISLE, Literal(6))
    slow, _ = a.write([], [five], 10, is_base)
    fast, _ = b.write([], [six], 20, is_base)
    assert values(a, ROBOT1) == {Literal(5)}  # over the file's value (BASE_STAMP)
    assert a.apply(fast, is_base) == Effect(removed=frozenset({five}), added=frozenset({six}))
    assert b.apply(slow, is_base) == Effect()  # shadowed: nothing visible changes
    c.apply(fast, is_base)
    c.apply(slow, is_base)
    for r in (a, b, c):
        assert values(r, ROBOT1) == {Literal(6)}
        assert set(r.entries) == {five, six}  # the loser stays, shadowed
    assert a.equal_to(b) and b.equal_to(c)

    # Removing the winner removes what it shadows (the other write, the file's value).
    gone, effect = c.write([six], [], 30, is_base)
    assert set(gone.removed) == {slow.dot, fast.dot}
    assert gone.removed_base == ((ROBOT1, AISLE, AISLES[0]),)
    assert effect == Effect(removed=frozenset({six}))
    for r in (a, b):
        r.apply(gone, is_base)
    for r in (a, b, c):
        assert values(r, ROBOT1) == set() and not r.entries
    assert a.equal_to(b) and b.equal_to(c)


def test_same_millisecond_is_broken_by_the_writer() -> None:
    a, b = replica("A.1"), replica("B.1")
    da, _ = a.write([], [(ROBOT2, AISLE, Literal(2))], 7, is_base)
    db, _ = b.write([], [(ROBOT2, AISLE, Literal(3))], 7, is_base)
    a.apply(db, is_base)
    b.apply(da, is_base)
    assert values(a, ROBOT2) == values(b, ROBOT2) == {Literal(3)}  # "B.1" > "A.1"


def test_a_write_after_a_later_stamp_wins_even_with_a_slow_clock() -> None:
    a, b = replica("A.1"), replica("B.1")
    ahead, _ = b.write([], [(ROBOT2, AISLE, Literal(2))], 1_000, is_base)
    a.apply(ahead, is_base)
    # A's wall clock is far behind, but it saw B's stamp: its next write is newer.
    behind, _ = a.write([], [(ROBOT2, AISLE, Literal(3))], 5, is_base)
    assert behind.stamp == Stamp(1_000, 1, "A.1") and behind.stamp > ahead.stamp
    b.apply(behind, is_base)
    assert values(a, ROBOT2) == values(b, ROBOT2) == {Literal(3)}


def test_a_concurrent_value_survives_removing_the_winner() -> None:
    a, b = replica("A.1"), replica("B.1")
    first, _ = a.write([], [(ROBOT1, AISLE, Literal(5))], 10, is_base)
    b.apply(first, is_base)
    gone, _ = a.write([(ROBOT1, AISLE, Literal(5))], [], 11, is_base)
    moved, _ = b.write([], [(ROBOT1, AISLE, Literal(7))], 12, is_base)
    a.apply(moved, is_base)
    b.apply(gone, is_base)
    assert values(a, ROBOT1) == values(b, ROBOT1) == {Literal(7)} and a.equal_to(b)


# --------------------------------------------------------------------------- journal and catch-up


def test_missing_for_gives_only_the_missed_deltas_in_order() -> None:
    a, b = replica("A.1"), replica("B.1")
    deltas = [a.write([], [UNIVERSE[i]], i, is_base)[0] for i in (3, 4, 5)]
    b.apply(deltas[0], is_base)
    assert a.missing_for(b.context) == deltas[1:]
    assert a.missing_for(a.context) == []
    assert b.missing_for(a.context) == []
    # A peer's delta is journaled too, so B can pass on what it got.
    assert b.missing_for(CausalContext()) == deltas[:1]


def test_a_compacted_journal_falls_back_to_the_whole_state() -> None:
    a, b, c = replica("A.1"), replica("B.1"), replica("C.1")
    deltas = [a.write([], [UNIVERSE[i]], i, is_base)[0] for i in (3, 4, 5)]
    a.write([FILE_TRIPLE], [], 9, is_base)  # removes a file triple
    b.apply(deltas[0], is_base)
    assert a.compact([b.context]) == 1  # only what every peer given has seen
    assert list(a.journal) == [Dot("A.1", 2), Dot("A.1", 3), Dot("A.1", 4)]
    assert [d.dot for d in a.missing_for(b.context)] == [Dot("A.1", 2), Dot("A.1", 3), Dot("A.1", 4)]
    state = a.missing_for(c.context)  # C needs A.1:1, which is gone
    assert isinstance(state, WrittenState)
    assert state.removed_base == {FILE_TRIPLE}
    c.join(state, is_base)
    assert c.equal_to(a) and visible(c) == visible(a)
    assert a.compact([b.context, c.context]) == 0  # B still lacks the rest
    assert a.compact([c.context]) == 3 and a.journal_size == 0


def test_the_journal_bound_forgets_the_oldest_and_the_state_still_converges() -> None:
    a, b = replica("A.1", limits=ReplicaLimits(journal_max=5)), replica("B.1")
    for i in range(6):
        a.write([], [UNIVERSE[i]], i, is_base)  # size 2 each
        assert a.journal_size <= 5
    assert list(a.journal) == [Dot("A.1", 5), Dot("A.1", 6)]
    changes = a.missing_for(b.context)
    assert isinstance(changes, WrittenState)
    b.join(changes, is_base)
    assert b.equal_to(a) and visible(b) == visible(a)
    # One delta bigger than the bound is still kept: the newest always is.
    big, _ = a.write([], UNIVERSE[6:12], 10, is_base)
    assert list(a.journal) == [big.dot] and a.journal_size == big.size > 5


def test_the_entries_bound_refuses_a_local_write_and_changes_nothing() -> None:
    limits = ReplicaLimits(entries_max=2)
    a, b = replica("A.1", limits=limits), replica("B.1")
    a.write([], [UNIVERSE[0], UNIVERSE[1]], 1, is_base)
    before, journal, shown = a.state(), list(a.journal), visible(a)
    with pytest.raises(ReplicaFull):
        a.write([UNIVERSE[0]], [UNIVERSE[2]], 2, is_base)
    assert a.state() == before and list(a.journal) == journal and visible(a) == shown
    # Re-adding a triple it holds costs no entry, and the sequence did not skip.
    again, _ = a.write([], [UNIVERSE[1]], 3, is_base)
    assert again.dot == Dot("A.1", 3)  # the first write took a dot per triple: 1 and 2
    # A peer's write is joined past the bound: refusing it would split the team.
    theirs, _ = b.write([], [UNIVERSE[5]], 4, is_base)
    assert a.apply(theirs, is_base) and len(a.entries) == 3


def test_the_cloud_bound_holds_against_deltas_past_gaps() -> None:
    a = replica("A.1", limits=ReplicaLimits(cloud_max=2))
    for seq in (2, 4, 6, 8, 10):  # every other one lost
        a.apply(Delta(Dot("B.1", seq), Stamp(seq, 0, "B.1"), added=(UNIVERSE[seq],)), is_base)
    assert a.gaps() <= 2


def test_replica_limits_must_be_positive() -> None:
    for name in ("journal_max", "entries_max", "cloud_max"):
        with pytest.raises(ValueError, match=name):
            ReplicaLimits(**{name: 0})


# --------------------------------------------------------------------------- causal context


def test_causal_context_add_fills_gaps_into_the_version_vector() -> None:
    c = CausalContext()
    c.add(Dot("A", 1))
    c.add(Dot("A", 3))
    c.add(Dot("B", 2))
    assert c.vv == {"A": 1} and c.cloud == {Dot("A", 3), Dot("B", 2)}
    assert Dot("A", 1) in c and Dot("A", 2) not in c and Dot("A", 3) in c
    c.add(Dot("A", 2))  # the gap closes: the cloud compacts
    assert c.vv == {"A": 3} and c.cloud == {Dot("B", 2)}
    c.add(Dot("A", 2))  # seen: nothing changes
    assert c == CausalContext({"A": 3}, [Dot("B", 2)])
    assert c.summary() == (("A", 3), ("B", -2))


def test_causal_context_merge_compacts_the_cloud() -> None:
    mine = CausalContext({"A": 1}, [Dot("A", 3), Dot("A", 5), Dot("B", 4)])
    theirs = CausalContext({"A": 2, "B": 3}, [Dot("A", 6)])
    assert {*mine.missing_from(theirs)} == {Dot("A", 3), Dot("A", 5), Dot("B", 4)}
    assert {*theirs.missing_from(mine)} == {Dot("A", 2), Dot("B", 1), Dot("B", 2), Dot("B", 3), Dot("A", 6)}
    mine.merge(theirs)
    assert mine == CausalContext({"A": 3, "B": 4}, [Dot("A", 5), Dot("A", 6)])
    assert mine.covers(theirs) and not theirs.covers(mine)
    copy = mine.copy()
    copy.add(Dot("A", 4))
    assert copy.vv == {"A": 6, "B": 4} and not copy.cloud and mine.vv["A"] == 3  # a copy is separate


_dots = st.lists(st.builds(Dot, st.sampled_from(["A", "B", "C"]), st.integers(1, 12)), max_size=30)


@settings(max_examples=200, deadline=None)
@given(dots=_dots, split=st.integers(0, 30), order=st.randoms(use_true_random=False))
def test_causal_context_is_the_set_of_its_dots_in_any_order(dots: list[Dot], split: int, order: random.Random) -> None:
    whole = CausalContext(cloud=dots)
    shuffled = list(dots)
    order.shuffle(shuffled)
    left, right = CausalContext(cloud=shuffled[:split]), CausalContext(cloud=shuffled[split:])
    left.merge(right)
    assert left == whole  # one canonical form, whatever the order or grouping
    for writer in "ABC":
        for seq in range(1, 14):
            assert (Dot(writer, seq) in whole) == (Dot(writer, seq) in set(dots))
    for d in whole.cloud:  # compacted: nothing in the cloud the vector could hold
        assert d.seq > whole.vv.get(d.writer, 0) + 1
    assert set(whole.missing_from(CausalContext())) == set(dots)
    assert whole.covers(CausalContext(cloud=dots[: len(dots) // 2]))


# --------------------------------------------------------------------------- bounded, idempotent


def test_a_single_value_written_again_and_again_keeps_one_entry() -> None:
    """A robot's aisle written 1,000 times (INSERT DATA each time, as the
    robots write their position): the older values go with each write, so
    the written state stays one triple, on every replica alike."""
    a, b = replica("A.1"), replica("B.1")
    for i in range(1000):
        delta, _ = a.write([], [(ROBOT1, AISLE, AISLES[i % 3])], i, is_base)
        b.apply(delta, is_base)
    assert len(a.entries) == 1 and values(a, ROBOT1) == {AISLES[999 % 3]}
    assert b.entries == a.entries and values(b, ROBOT1) == values(a, ROBOT1)


def test_an_add_that_already_shows_as_this_writer_s_changes_nothing() -> None:
    a = replica("A.1")
    a.write([], [X], 1, is_base)
    assert a.unchanged_by([], [X], is_base)
    b = replica("B.1")
    b.apply(a.write([], [(ROBOT1, NEAR, THINGS[1])], 2, is_base)[0], is_base)
    # Another writer's triple is tagged again: its writer may remove it concurrently (add wins).
    assert not b.unchanged_by([], [(ROBOT1, NEAR, THINGS[1])], is_base)
