"""The replication message (coapkb/wire/sync.py): a holder's causal context
and the deltas, the whole written state, or nothing it sends.

* Round trips are exact: dots, stamps, removed dots, removed file triples
  and added triples, down to each literal's lexical form.
* Decoding arbitrary bytes, mutated valid messages, or well-formed CBOR of
  the wrong shape raises ``CodecError`` and nothing else.
* A one-triple delta stays small (it rides in one CoAP datagram).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cbor2
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from rdflib.term import Literal, URIRef

from coapkb.kb.replica import Replica
from coapkb.kb.update import encode_patch
from coapkb.model.deltas import CausalContext, Delta, Dot, MadeUnder, Stamp, WrittenState
from coapkb.model.results import Triple
from coapkb.wire.codec import CodecError
from coapkb.wire.sync import Life, SyncMessage, decode_sync, encode_sync

LOC = "http://www.tcs.org/2018/Location#"
XSD = "http://www.w3.org/2001/XMLSchema#"

# rdflib warns about the ill-typed literals mutated messages decode to.
pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def loc(name: str) -> URIRef:
    return URIRef(LOC + name)


AISLE: Triple = (loc("Robot1"), loc("Robot_aisle_no"), Literal(4))
NEAR: Triple = (loc("Robot1"), loc("near"), loc("Rack_3"))
LABEL: Triple = (loc("Rack_3"), loc("label"), Literal("étagère", lang="fr"))
WEIGHT: Triple = (loc("Rack_3"), loc("load"), Literal("01.50", datatype=URIRef(XSD + "decimal")))
FILE_TRIPLE: Triple = (loc("Robot1"), loc("Robot_aisle_no"), Literal(9))


def exact(triples: tuple[Triple, ...]) -> list[tuple[object, ...]]:
    """Every field of every term (rdflib's == is lenient about language tags)."""
    return [tuple((type(t), str(t), getattr(t, "datatype", None), getattr(t, "language", None)) for t in tr)
            for tr in triples]


def same_delta(got: Delta, sent: Delta) -> None:
    assert (got.dot, got.stamp) == (sent.dot, sent.stamp)
    assert exact(got.added) == exact(sent.added) and exact(got.removed_base) == exact(sent.removed_base)
    assert sorted(got.removed) == sorted(sent.removed)  # grouped by writer on the wire


def round_trip(message: SyncMessage) -> SyncMessage:
    got = decode_sync(encode_sync(message))
    assert got.module == message.module and got.context == message.context
    return got


CONTEXT = CausalContext({"Robot1.7": 12, "Robot2.1": 3}, [Dot("Robot2.1", 5), Dot("Robot3.2", 2)])


def test_deltas_round_trip() -> None:
    deltas = [
        Delta(Dot("Robot1.7", 13), Stamp(1_700_000_000_123, 2, "Robot1.7"), added=(AISLE, LABEL, WEIGHT),
              removed=(Dot("Robot1.7", 4), Dot("Robot1.7", 9), Dot("Robot2.1", 1)), removed_base=(FILE_TRIPLE,)),
        Delta(Dot("Robot2.1", 6), Stamp(5, 0, "Robot2.1")),  # nothing but its dot: an empty write
        Delta(Dot("Robot3.2", 1), Stamp(7, 1, "Robot3.2"), added=(NEAR,)),
    ]
    got = round_trip(SyncMessage("Location", CONTEXT, deltas))
    assert isinstance(got.changes, list) and len(got.changes) == len(deltas)
    for g, d in zip(got.changes, deltas):
        same_delta(g, d)
    assert got.changes[0] == deltas[0]  # the replica's sorted removed dots keep their order too


#: A robot's write under OSCORE (its sender is its writer's robot, left out
#: on the wire), and a script's on an unprotected team.
MADE = (MadeUnder("Robot2", "Robot2.7f3a", "12", b"\x01" * 8, 1, 1),
        MadeUnder(None, "op.7", "3", b"\x02" * 8, 0, 4))


@pytest.mark.parametrize("made", MADE)
def test_the_id_of_a_pushed_write_round_trips(made: MadeUnder) -> None:
    push = SyncMessage("Location", CONTEXT, [Delta(Dot("Robot1.7", 13), Stamp(5, 0, "Robot1.7"), added=(AISLE,))],
                       made=made)
    got = round_trip(push)
    assert got.made == made and not got.forward
    if made.peer is not None:  # the sender left out: the id, its digest and two counts
        assert len(encode_sync(push)) - len(encode_sync(replace(push, made=None))) <= 30


def test_a_life_and_the_lives_known_round_trip() -> None:
    question = SyncMessage("Location", CONTEXT, life=Life("Robot1", 4))
    answer = SyncMessage("Location", CONTEXT, lives={"Robot1": 4, "Robot3": 2})
    assert round_trip(question) == question and round_trip(answer) == answer
    # A life costs a push its robot's name and number, as the fence needs.
    assert len(encode_sync(question)) - len(encode_sync(replace(question, life=None))) <= 13


def test_a_written_state_round_trips() -> None:
    state = WrittenState(
        CONTEXT,
        {
            AISLE: {Dot("Robot1.7", 12): Stamp(40, 0, "Robot1.7"), Dot("Robot2.1", 5): Stamp(41, 3, "Robot2.1")},
            LABEL: {Dot("Robot3.2", 2): Stamp(2, 0, "Robot3.2")},
            WEIGHT: {Dot("Robot1.7", 1): Stamp(1, 0, "Robot1.7")},
        },
        frozenset({FILE_TRIPLE, NEAR}),
    )
    got = round_trip(SyncMessage("Location", CONTEXT, state))
    assert got.changes == state
    assert isinstance(got.changes, WrittenState)
    assert exact(tuple(got.changes.entries)) == exact(tuple(state.entries))


def test_a_replicas_own_messages_round_trip_and_join() -> None:
    # What a holder really sends: its deltas, then its state, to a peer that joins them.
    a, b, c = Replica("A.1"), Replica("B.1"), Replica("C.1")
    never = lambda t: t == FILE_TRIPLE  # noqa: E731
    d1, _ = a.write([], [AISLE, NEAR], 10, never)
    d2, _ = a.write([NEAR, FILE_TRIPLE], [LABEL], 11, never)
    got = round_trip(SyncMessage("Location", a.context, [d1, d2]))
    assert got.changes == [d1, d2]
    for delta in got.changes:
        b.apply(delta, never)
    state = round_trip(SyncMessage("Location", a.context, a.state())).changes
    assert isinstance(state, WrittenState)
    c.join(state, never)
    assert a.equal_to(b) and a.equal_to(c)


def test_only_a_context_round_trips() -> None:
    for context in (CausalContext(), CONTEXT, CausalContext(cloud=[Dot("x", 3)])):
        got = round_trip(SyncMessage("Object", context, None))
        assert got.changes is None
    assert round_trip(SyncMessage("Object", CONTEXT, [])).changes == []


def test_a_one_triple_delta_is_small() -> None:
    delta = Delta(Dot("Robot1.1700000000", 42), Stamp(1_700_000_000_123, 0, "Robot1.1700000000"), added=(AISLE,),
                  removed=(Dot("Robot1.1700000000", 41),))
    context = CausalContext({"Robot1.1700000000": 42, "Robot2.1700000000": 17})
    size = len(encode_sync(SyncMessage("Location", context, [delta])))
    assert size < 250, size


# --------------------------------------------------------------------------- garbage


def _valid_messages() -> list[bytes]:
    delta = Delta(Dot("A.1", 2), Stamp(9, 1, "A.1"), added=(AISLE, LABEL), removed=(Dot("A.1", 1), Dot("B.1", 3)),
                  removed_base=(FILE_TRIPLE,))
    state = WrittenState(CONTEXT, {AISLE: {Dot("A.1", 2): Stamp(9, 1, "A.1")}}, frozenset({FILE_TRIPLE}))
    return [encode_sync(SyncMessage("Location", CONTEXT, changes)) for changes in ([delta], state, None)]


VALID = _valid_messages()


@st.composite
def mutated(draw: st.DrawFn) -> bytes:
    data = bytearray(draw(st.sampled_from(VALID)))
    for _ in range(draw(st.integers(1, 4))):
        at = draw(st.integers(0, len(data) - 1))
        how = draw(st.integers(0, 3))
        if how == 0:
            data[at] = draw(st.integers(0, 255))
        elif how == 1:
            data.insert(at, draw(st.integers(0, 255)))
        elif how == 2 and len(data) > 1:
            del data[at]
        else:
            data = data[:at] or data
    return bytes(data)


_leaf = (st.none() | st.booleans() | st.integers(-3, 2**65) | st.floats(allow_nan=True)
         | st.text(max_size=6) | st.binary(max_size=6))
_cbor = st.recursive(
    _leaf,
    lambda inner: st.lists(inner, max_size=4)
    | st.dictionaries(st.integers(0, 5) | st.text(max_size=2), inner, max_size=4)
    | st.builds(cbor2.CBORTag, st.sampled_from([2, 24, 6, 256, 99]), inner),
    max_leaves=16,
)
_graph = st.sampled_from([cbor2.loads(VALID[0])[2][0], cbor2.CBORTag(24, b"\xf6"), cbor2.CBORTag(24, b"\x81")])


@st.composite
def shaped(draw: st.DrawFn) -> bytes:
    """The message's skeleton with wrong parts: gets past the CBOR decoder."""
    delta = [draw(st.sampled_from(["A.1", "", 3])), draw(st.integers(-1, 3)), draw(st.integers(0, 9) | _leaf),
             draw(st.integers(0, 9) | _leaf), draw(st.lists(_cbor, max_size=2) | _leaf),
             draw(st.integers(-1, 3) | _cbor), draw(st.integers(-1, 3) | _cbor)]
    state = {k: draw(_cbor | _graph) for k in draw(st.sets(st.integers(0, 5), max_size=5))}
    graph = draw(_graph | _cbor)
    changes = draw(st.sampled_from([None, [graph, [delta]], state, [graph, [delta, delta]]]) | _cbor)
    context = draw(st.lists(st.lists(_cbor, max_size=4), max_size=3) | _cbor)
    return cbor2.dumps([draw(st.sampled_from(["Location", "", 7])), context, changes])


@settings(max_examples=500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.binary(max_size=300) | mutated() | _cbor.map(cbor2.dumps) | shaped())
@example(data=b"")
@example(data=cbor2.dumps(["Location", [["A.1", 2**64]], None]))
@example(data=cbor2.dumps(["Location", [], {1: [], 2: cbor2.CBORTag(24, b"\xf6"), 3: [], 4: 1}]))
def test_garbage_raises_only_codec_error(data: bytes) -> None:
    try:
        message = decode_sync(data)
    except CodecError:
        return
    # Whatever decodes encodes, and decodes to the same again.
    again = decode_sync(encode_sync(message))
    assert again.module == message.module and again.context == message.context
    if isinstance(message.changes, list):
        assert isinstance(again.changes, list) and len(again.changes) == len(message.changes)
        for g, d in zip(again.changes, message.changes):
            same_delta(g, d)
    else:
        assert again.changes == message.changes


@pytest.mark.parametrize(
    "item",
    [
        ["Location", []],  # no changes field
        ["", [], None],  # no module name
        ["Location", [["A.1"]], None],  # a context entry without its top
        ["Location", [["A.1", -1]], None],
        ["Location", [["A.1", True]], None],  # a bool is no count
        ["Location", [], [cbor2.loads(VALID[0])[2][0], [["A.1", 0, 1, 0, [], 0, 0]]]],  # seq 0
        ["Location", [], [b"", [["A.1", 1, 1, 0, [], 0, 0]]]],  # the graph not tagged
        ["Location", [], [cbor2.loads(VALID[0])[2][0], [["A.1", 1, 1, 0, [], 0, 9]]]],  # more counted than sent
        ["Location", [], [cbor2.loads(VALID[0])[2][0], [["A.1", 1, 1, 0, [], 0, 0]]]],  # sent, not counted
        ["Location", [], {1: [], 2: cbor2.loads(VALID[1])[2][2], 3: [], 4: cbor2.loads(VALID[1])[2][4]}],
        ["Location", [], None, False, None, ["Robot1"]],  # a life without its number
        ["Location", [], None, False, None, ["Robot1", -2]],
        ["Location", [], None, False, None, None, {"Robot1": "4"}],  # a life number as text
        ["Location", [], None, False, None, None, [["Robot1", 4]]],  # lives not a map
    ],
)
def test_wrong_shapes_are_codec_errors(item: object) -> None:
    with pytest.raises(CodecError):
        decode_sync(cbor2.dumps(item))


# --------------------------------------------------------------------------- the specification


@pytest.fixture(scope="module")
def knowledge_cddl() -> object:
    """docs/knowledge.cddl with the compact results' rules it embeds."""
    cddl_verifier = pytest.importorskip("cddl_verifier")
    docs = Path(__file__).resolve().parents[2] / "docs"
    text = (docs / "knowledge.cddl").read_text() + "\n" + (docs / "compact-results.cddl").read_text()
    return cddl_verifier.Validator(text)


def test_sync_messages_match_the_cddl(knowledge_cddl: object) -> None:
    a, b = Replica("A.1"), Replica("B.1")
    first, _ = a.write([], [AISLE, NEAR, LABEL], 1, lambda t: False)
    second, _ = a.write([NEAR, FILE_TRIPLE], [WEIGHT], 2, lambda t: t == FILE_TRIPLE)
    b.apply(second, lambda t: False)  # before the first: a tombstone for NEAR's dot
    messages = [
        SyncMessage("Location", a.context, [first, second]),
        SyncMessage("Location", a.context, [second], forward=True),
        SyncMessage("Location", a.context, [first], made=MADE[0]),
        SyncMessage("Location", a.context, [first], forward=True, made=MADE[1]),
        SyncMessage("Location", b.context, b.state()),
        SyncMessage("Location", CausalContext()),
        SyncMessage("Location", a.context, [first], life=Life("A", 3)),
        SyncMessage("Location", a.context, life=Life("A", 3)),
        SyncMessage("Location", b.context, b.state(), lives={"A": 3, "B": 1}),
        SyncMessage("Location", a.context, [first], forward=True, made=MADE[1], life=Life("A", 1), lives={"A": 1}),
    ]
    assert b.state().tombstones
    for message in messages:
        outcome = knowledge_cddl.validate(encode_sync(message), root_type="sync")  # type: ignore[attr-defined]
        assert outcome.valid, [str(d) for d in outcome.diagnostics]


def test_a_patch_matches_the_cddl(knowledge_cddl: object) -> None:
    outcome = knowledge_cddl.validate(encode_patch([FILE_TRIPLE], [AISLE, LABEL]), root_type="patch")  # type: ignore[attr-defined]
    assert outcome.valid, [str(d) for d in outcome.diagnostics]


def test_named_updates_match_the_cddl(knowledge_cddl: object) -> None:
    from coapkb.kb.named_updates import NamedUpdate, encode_named_updates

    writes = [[NamedUpdate("pick", ("Gucci_bag_14", "Robot2", 7)), NamedUpdate("robot-at", ("Robot2", 3, 21, 1000)),
               NamedUpdate("delivered", ("Gucci_bag_14", 7)), NamedUpdate("restock", ("Gucci_bag_14", 3, 21, 2)),
               NamedUpdate("missing", ("Canon_tv_538", "Robot1", 8))],
              [NamedUpdate("load", ("Robot1", 12.5, 380, 4000))]]
    for write in writes:
        outcome = knowledge_cddl.validate(encode_named_updates(write), root_type="named-updates")  # type: ignore[attr-defined]
        assert outcome.valid, [str(d) for d in outcome.diagnostics]


def test_a_write_answer_matches_the_cddl(knowledge_cddl: object) -> None:
    from coapkb.kb.write_concern import Ack, Reached, encode_changed

    for level in Ack:
        outcome = knowledge_cddl.validate(encode_changed(1, 2, Reached(level)), root_type="write-answer")  # type: ignore[attr-defined]
        assert outcome.valid, [str(d) for d in outcome.diagnostics]
