"""Writes to a module: SPARQL 1.1 Update split into operations
(coapkb/kb/update.py), the compact patch, and a live KB running them
(coapkb/kb/live.py).

* Each supported form parses; every refused keyword is named; malformed
  text is a syntax error with its line and column.
* The compact patch round-trips, and garbage gives only ``CodecError``.
* A write changes the view queries see, never the files' graph; it is
  refused whole (module not held, stale If-Match, too many triples, blank
  nodes); two holders that exchange their deltas end at the same version.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from pathlib import Path

import cbor2
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rdflib.term import BNode, Literal, URIRef
from support import ONTOLOGIES

from coapkb.kb.errors import QuerySyntaxError
from coapkb.kb.live import LiveKB, NotHeld, PreconditionFailed, WriteLimits, WriteTooLarge
from coapkb.kb.store import KnowledgeBase
from coapkb.kb.update import Operation, UpdateUnsupported, decode_patch, encode_patch, parse_update
from coapkb.model.results import SelectResult, Triple
from coapkb.wire.codec import CodecError

LOC = "http://www.tcs.org/2018/Location#"
OBJ = "http://www.tcs.org/2018/Object#"
XSD = "http://www.w3.org/2001/XMLSchema#"
PREFIX = f"PREFIX loc: <{LOC}>\n"
KB_FILES = [ONTOLOGIES / f"{n}.owl" for n in ("Location", "Object", "Capability")]
AISLE_OF_ROBOT1 = PREFIX + "SELECT ?a WHERE { loc:Robot1 loc:Robot_aisle_no ?a }"
MOVE_ROBOT1 = PREFIX + (
    "DELETE { loc:Robot1 loc:Robot_aisle_no ?a } INSERT { loc:Robot1 loc:Robot_aisle_no %d } "
    "WHERE { loc:Robot1 loc:Robot_aisle_no ?a }"
)


#: One triple for the Location module, one for the Object module.
TWO_MODULES = PREFIX + f"INSERT DATA {{ loc:Robot42 loc:near loc:Rack_3 . <{OBJ}Shoe_2> loc:near loc:Rack_3 }}"


def loc(name: str) -> URIRef:
    return URIRef(LOC + name)


# --------------------------------------------------------------------------- parsing


@pytest.mark.parametrize(
    ("text", "kind", "parts"),
    [
        ("INSERT DATA { loc:a loc:b loc:c }", "INSERT DATA", {"insert": " loc:a loc:b loc:c "}),
        ("DELETE DATA { loc:a loc:b 1 }", "DELETE DATA", {"delete": " loc:a loc:b 1 "}),
        ("DELETE WHERE { loc:a loc:b ?o }", "DELETE WHERE", {"where": " loc:a loc:b ?o "}),
        ("DELETE { ?s loc:b ?o } INSERT { ?s loc:c ?o } WHERE { ?s loc:b ?o }", "MODIFY",
         {"delete": " ?s loc:b ?o ", "insert": " ?s loc:c ?o ", "where": " ?s loc:b ?o "}),
        ("DELETE { ?s loc:b ?o } WHERE { ?s loc:b ?o FILTER(?o > 3) }", "MODIFY",
         {"delete": " ?s loc:b ?o ", "where": " ?s loc:b ?o FILTER(?o > 3) "}),
        ("INSERT { ?s loc:c 1 } WHERE { ?s loc:b ?o }", "MODIFY", {"insert": " ?s loc:c 1 ", "where": " ?s loc:b ?o "}),
        # Keywords in any case; braces, ';' and keywords inside strings and comments are text.
        ('insert data { loc:a loc:b "LOAD } ; {" } # DROP ALL', "INSERT DATA",
         {"insert": ' loc:a loc:b "LOAD } ; {" '}),
        ("DELETE WHERE { loc:a loc:b ?o . ?o loc:c ?p }", "DELETE WHERE", {"where": " loc:a loc:b ?o . ?o loc:c ?p "}),
    ],
)
def test_each_supported_form_parses(text: str, kind: str, parts: dict[str, str]) -> None:
    parsed = parse_update(PREFIX + text)
    assert parsed.prologue == PREFIX.strip()
    assert parsed.operations == (Operation(kind, **parts),)


def test_a_sequence_shares_its_prologue() -> None:
    text = (
        f"BASE <{LOC}>\nPREFIX loc: <{LOC}>\nPREFIX obj: <{OBJ}>\n"
        "INSERT DATA { loc:a loc:b obj:c } ;\n"
        "DELETE WHERE { loc:a loc:b ?o } ;\n"
        "DELETE { ?s ?p ?o } INSERT { ?s ?p 2 } WHERE { ?s ?p ?o } ;"  # a trailing ';' is allowed
    )
    parsed = parse_update(text)
    assert parsed.prologue == f"BASE <{LOC}>\nPREFIX loc: <{LOC}>\nPREFIX obj: <{OBJ}>"
    assert [op.kind for op in parsed.operations] == ["INSERT DATA", "DELETE WHERE", "MODIFY"]
    assert [op.reads_module for op in parsed.operations] == [False, True, True]
    removes, adds = parsed.operations[0].queries(parsed.prologue)
    assert removes is None and adds is not None and adds.startswith(parsed.prologue) and "CONSTRUCT" in adds


@pytest.mark.parametrize(
    ("text", "keyword"),
    [
        ("LOAD <http://example.org/data.ttl>", "LOAD"),
        ("CLEAR DEFAULT", "CLEAR"),
        ("CLEAR ALL", "CLEAR"),
        ("DROP GRAPH <http://example.org/g>", "DROP"),
        ("CREATE GRAPH <http://example.org/g>", "CREATE"),
        ("ADD DEFAULT TO <http://example.org/g>", "ADD"),
        ("MOVE DEFAULT TO <http://example.org/g>", "MOVE"),
        ("COPY DEFAULT TO <http://example.org/g>", "COPY"),
        ("WITH <http://example.org/g> DELETE { ?s ?p ?o } WHERE { ?s ?p ?o }", "WITH"),
        ("DELETE { ?s ?p ?o } USING <http://example.org/g> WHERE { ?s ?p ?o }", "USING"),
        ("INSERT DATA { GRAPH <http://example.org/g> { loc:a loc:b loc:c } }", "GRAPH"),
        ("DELETE WHERE { GRAPH ?g { ?s ?p ?o } }", "GRAPH"),
        ("DELETE { ?s ?p ?o } WHERE { SERVICE <http://example.org/sparql> { ?s ?p ?o } }", "SERVICE"),
        # After a supported operation, and inside text that is otherwise malformed:
        # a refused keyword is named first, and never reaches the store's parser.
        ("INSERT DATA { loc:a loc:b loc:c } ; LOAD <http://example.org/x>", "LOAD"),
        ("INSERT DATA {{ LOAD <http://example.org/x>", "LOAD"),
    ],
)
def test_unsupported_operations_are_refused_by_name(text: str, keyword: str) -> None:
    with pytest.raises(UpdateUnsupported) as refused:
        parse_update(PREFIX + text)
    assert str(refused.value).startswith(keyword + ":"), refused.value


def test_a_malformed_update_is_a_syntax_error_with_its_position() -> None:
    text = 'PREFIX ex: <http://example.org/>\nINSERT DATA {\n  ex:a ex:b "unclosed\n}'
    with pytest.raises(QuerySyntaxError) as error:
        parse_update(text)
    assert error.value.line == 3
    assert error.value.column is not None and 1 <= error.value.column <= len('  ex:a ex:b "unclosed') + 1
    assert "line 3" in str(error.value)


@pytest.mark.parametrize(
    "text",
    [
        PREFIX + "SELECT ?s WHERE { ?s ?p ?o }",  # a query is not an update
        PREFIX + "ASK { ?s ?p ?o }",
        "",
        PREFIX,  # a prologue without an operation
        PREFIX + "INSERT DATA { loc:a loc:b }",
        PREFIX + "DELETE { ?s ?p ?o } { ?s ?p ?o }",  # no WHERE
    ],
)
def test_what_is_not_an_update_is_a_syntax_error(text: str) -> None:
    with pytest.raises(QuerySyntaxError):
        parse_update(text)


@pytest.mark.parametrize("local", ["Robot42", "Service", "graph"])
def test_the_empty_prefix_is_valid_sparql(local: str) -> None:
    parsed = parse_update(f"PREFIX : <{LOC}>\nINSERT DATA {{ :Robot1 :uses :{local} }}")
    assert [op.kind for op in parsed.operations] == ["INSERT DATA"]


# --------------------------------------------------------------------------- the compact patch


TRIPLES: list[Triple] = [
    (loc("Robot1"), loc("Robot_aisle_no"), Literal(4)),
    (loc("Robot1"), loc("near"), loc("Rack_3")),
    (URIRef(OBJ + "Shoe_2"), URIRef(OBJ + "label"), Literal("chaussure", lang="fr")),
    (URIRef(OBJ + "Shoe_2"), URIRef(OBJ + "weight"), Literal("0.50", datatype=URIRef(XSD + "decimal"))),
]


@pytest.mark.parametrize(("deletes", "inserts"), [(TRIPLES[:1], TRIPLES[1:]), ([], TRIPLES), (TRIPLES, []), ([], [])])
def test_a_patch_round_trips(deletes: list[Triple], inserts: list[Triple]) -> None:
    encoded = encode_patch(deletes, inserts)
    assert decode_patch(encoded) == (tuple(deletes), tuple(inserts))
    # Exact terms: the decimal's lexical form and the language tag survive.
    for got, sent in zip(decode_patch(encoded)[1], inserts):
        assert [str(t) for t in got] == [str(t) for t in sent]
        assert [getattr(t, "language", None) for t in got] == [getattr(t, "language", None) for t in sent]


def _mutations() -> st.SearchStrategy[bytes]:
    valid = encode_patch(TRIPLES[:2], TRIPLES[2:])
    return st.tuples(st.integers(0, len(valid) - 1), st.integers(0, 255), st.integers(0, 2)).map(
        lambda m: [
            valid[: m[0]] + bytes([m[1]]) + valid[m[0] + 1 :],  # one byte changed
            valid[: m[0]],  # cut short
            valid[: m[0]] + bytes([m[1]]) + valid[m[0] :],  # one byte inserted
        ][m[2]]
    )


_cbor = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.text(max_size=8) | st.binary(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.builds(cbor2.CBORTag, st.sampled_from([24, 6, 256, 1]), inner),
    max_leaves=12,
)


@settings(max_examples=400, deadline=None)
@given(data=st.binary(max_size=200) | _mutations() | _cbor.map(cbor2.dumps))
def test_a_garbage_patch_raises_only_codec_error(data: bytes) -> None:
    try:
        deletes, inserts = decode_patch(data)
    except CodecError:
        return
    assert decode_patch(encode_patch(deletes, inserts)) == (deletes, inserts)


def test_a_patch_is_two_graphs() -> None:
    for item in ([], [None], {1: 2}, [cbor2.CBORTag(24, b"\x80")] * 2, [1, 2, 3]):
        with pytest.raises(CodecError):
            decode_patch(cbor2.dumps(item))


# --------------------------------------------------------------------------- a live KB


class Clock:
    """A wall clock the test moves (the writes' stamps)."""

    def __init__(self, ms: int = 1_000) -> None:
        self.ms = ms

    def __call__(self) -> int:
        self.ms += 1
        return self.ms


def live(writer: str = "A.1", files: list = KB_FILES[:1], limits: WriteLimits | None = None) -> LiveKB:
    return LiveKB(KnowledgeBase.load(files), writer, wall_ms=Clock(), limits=limits)


def rows(kb: LiveKB | KnowledgeBase, sparql: str) -> set[tuple[object, ...]]:
    result = kb.query(sparql)
    assert isinstance(result, SelectResult)
    return set(result.rows)


@pytest.fixture
def kb() -> LiveKB:
    return live()


@pytest.fixture(scope="module", autouse=True)
def files_stay_as_they_are() -> Iterator[None]:
    # Writes copy the files' graph; the files themselves are never written.
    digests = {path: hashlib.sha256(path.read_bytes()).hexdigest() for path in ONTOLOGIES.glob("*.owl")}
    yield
    assert digests == {path: hashlib.sha256(path.read_bytes()).hexdigest() for path in ONTOLOGIES.glob("*.owl")}


def test_an_inserted_triple_is_seen_by_queries(kb: LiveKB) -> None:
    before = kb.etag
    written = kb.update(PREFIX + "INSERT DATA { loc:Robot42 loc:near loc:Rack_3 }")
    assert written.added == 1 and written.removed == 0 and set(written.deltas) == {"Location"}
    assert written.version == kb.etag != before
    assert rows(kb, PREFIX + "SELECT ?r WHERE { loc:Robot42 loc:near ?r }") == {(loc("Rack_3"),)}
    assert kb.triple_count == kb.base.triple_count + 1


def test_moving_a_robot_replaces_its_single_value(kb: LiveKB) -> None:
    assert rows(kb, AISLE_OF_ROBOT1) == {(Literal(9),)}  # from the file
    written = kb.update(MOVE_ROBOT1 % 4)
    assert written.removed == 1 and written.added == 1
    assert written.deltas["Location"].removed_base == ((loc("Robot1"), loc("Robot_aisle_no"), Literal(9)),)
    assert rows(kb, AISLE_OF_ROBOT1) == {(Literal(4),)}


def test_an_operation_reads_what_the_one_before_wrote(kb: LiveKB) -> None:
    written = kb.update(
        PREFIX + "INSERT DATA { loc:Robot42 loc:Robot_aisle_no 7 } ;\n"
        "INSERT { loc:Robot8 loc:follows ?a } WHERE { loc:Robot42 loc:Robot_aisle_no ?a } ;\n"
        "DELETE WHERE { loc:Robot42 loc:Robot_aisle_no ?a }"
    )
    assert written.deltas["Location"].added == ((loc("Robot8"), loc("follows"), Literal(7)),)
    assert rows(kb, PREFIX + "SELECT ?a WHERE { loc:Robot8 loc:follows ?a }") == {(Literal(7),)}
    assert rows(kb, PREFIX + "SELECT ?a WHERE { loc:Robot42 loc:Robot_aisle_no ?a }") == set()


def test_deleting_an_absent_triple_changes_nothing(kb: LiveKB) -> None:
    before = kb.etag
    written = kb.update(PREFIX + "DELETE DATA { loc:Robot1 loc:Robot_aisle_no 3 }")  # it is 9
    assert written.removed == 0 and written.added == 0 and not written.deltas
    assert kb.etag == before and rows(kb, AISLE_OF_ROBOT1) == {(Literal(9),)}
    assert kb.triple_count == kb.base.triple_count


def test_deleting_one_of_two_triples_inserted_together_keeps_the_other(kb: LiveKB) -> None:
    kb.update(PREFIX + "INSERT DATA { loc:Robot42 loc:near loc:Rack_1 , loc:Rack_2 }")
    kb.update(PREFIX + "DELETE DATA { loc:Robot42 loc:near loc:Rack_1 }")
    assert rows(kb, PREFIX + "SELECT ?r WHERE { loc:Robot42 loc:near ?r }") == {(loc("Rack_2"),)}


@pytest.mark.parametrize(
    "text",
    [
        "INSERT DATA { loc:Robot42 loc:near _:somewhere }",
        "INSERT DATA { loc:Robot42 loc:near [ loc:label 'x' ] }",
        "INSERT { ?r loc:near [] } WHERE { ?r loc:Robot_aisle_no 9 }",
    ],
)
def test_blank_nodes_are_refused(kb: LiveKB, text: str) -> None:
    before = kb.etag
    with pytest.raises(UpdateUnsupported, match="blank node"):
        kb.update(PREFIX + text)
    with pytest.raises(UpdateUnsupported, match="blank node"):
        kb.patch([], [(loc("Robot42"), loc("near"), BNode())])
    assert kb.etag == before and not kb.changed


def test_a_module_the_robot_does_not_hold_is_refused_whole(kb: LiveKB) -> None:
    before = kb.etag
    with pytest.raises(NotHeld) as refused:
        kb.update(TWO_MODULES)
    assert refused.value.module == "Object"
    assert kb.etag == before and not kb.replicas["Location"].entries


def test_a_write_goes_to_the_module_of_its_subject() -> None:
    kb = live(files=KB_FILES)
    written = kb.update(TWO_MODULES)
    assert set(written.deltas) == {"Location", "Object"}
    assert kb.module_version("Capability") == live(files=KB_FILES).module_version("Capability")
    assert kb.module_version("Location") != live(files=KB_FILES).module_version("Location")


def test_if_match_makes_a_write_conditional(kb: LiveKB) -> None:
    stale = kb.etag
    kb.update(PREFIX + "INSERT DATA { loc:Robot42 loc:near loc:Rack_3 }", if_match=(stale,))
    current = kb.etag
    for write in (
        lambda: kb.update(MOVE_ROBOT1 % 2, if_match=(stale,)),
        lambda: kb.patch([], [(loc("Robot42"), loc("near"), loc("Rack_4"))], if_match=(stale,)),
    ):
        with pytest.raises(PreconditionFailed):
            write()
        assert kb.etag == current
    kb.update(MOVE_ROBOT1 % 2, if_match=(stale, current))  # any one that matches
    kb.update(MOVE_ROBOT1 % 3, if_match=(b"",))  # empty: only that the KB exists
    assert rows(kb, AISLE_OF_ROBOT1) == {(Literal(3),)}


def test_a_write_of_too_many_triples_is_refused() -> None:
    kb = live(limits=WriteLimits(max_triples=3))
    many = " ".join(f"loc:Robot42 loc:near loc:Rack_{i} ." for i in range(4))
    with pytest.raises(WriteTooLarge):
        kb.update(PREFIX + f"INSERT DATA {{ {many} }}")
    with pytest.raises(WriteTooLarge):
        kb.update(PREFIX + "DELETE WHERE { ?r loc:Robot_aisle_no ?a }")  # 8 robots in the file
    with pytest.raises(WriteTooLarge):
        kb.patch([], [(loc("Robot42"), loc("near"), loc(f"Rack_{i}")) for i in range(4)])
    assert not kb.replicas["Location"].entries and not kb.changed
    three = " ".join(f"loc:Robot42 loc:near loc:Rack_{i} ." for i in range(3))
    assert kb.update(PREFIX + f"INSERT DATA {{ {three} }}").added == 3  # the bound itself is fine


def test_a_patch_writes_like_an_update(kb: LiveKB) -> None:
    deletes, inserts = decode_patch(encode_patch(
        [(loc("Robot1"), loc("Robot_aisle_no"), Literal(9)), (loc("Robot1"), loc("near"), loc("Nowhere"))],
        [(loc("Robot1"), loc("Robot_aisle_no"), Literal(5))],
    ))
    written = kb.patch(deletes, inserts)
    assert written.removed == 1 and written.added == 1  # the absent triple is not removed
    assert rows(kb, AISLE_OF_ROBOT1) == {(Literal(5),)}


def test_two_holders_exchanging_deltas_agree() -> None:
    a, b = live("A.1"), live("B.1")
    assert a.etag == b.etag  # the files alone
    mine = a.update(MOVE_ROBOT1 % 4).deltas["Location"]
    theirs = b.update(PREFIX + "INSERT DATA { loc:Robot42 loc:near loc:Rack_3 }").deltas["Location"]
    later = b.update(MOVE_ROBOT1 % 6).deltas["Location"]  # B's clock is later: its value wins
    assert a.apply("Location", [theirs, later])
    assert not b.apply("Location", [mine])  # joined, but shadowed by B's later move: nothing shows
    assert not a.apply("Location", [theirs])  # a duplicate changes nothing
    assert a.etag == b.etag and a.module_version("Location") == b.module_version("Location")
    assert a.replicas["Location"].equal_to(b.replicas["Location"])
    everything = "SELECT ?s ?p ?o WHERE { ?s ?p ?o }"
    assert rows(a, everything) == rows(b, everything)
    assert rows(a, AISLE_OF_ROBOT1) == {(Literal(6),)}
    # A third holder catches up from the whole state.
    c = live("C.1")
    assert c.join("Location", a.replicas["Location"].state())
    assert c.etag == a.etag and rows(c, everything) == rows(a, everything)


def test_the_files_graph_is_never_written() -> None:
    base = KnowledgeBase.load(KB_FILES[:1])
    kb = LiveKB(base, "A.1", wall_ms=Clock())
    files_etag, files_rows = base.etag, rows(base, AISLE_OF_ROBOT1)
    kb.update(MOVE_ROBOT1 % 4)
    kb.update(PREFIX + "INSERT DATA { loc:Robot42 loc:near loc:Rack_3 }")
    assert rows(kb, AISLE_OF_ROBOT1) == {(Literal(4),)}
    # The KB loaded from the files, and a fresh load of them, still say the files' values.
    for files in (base, KnowledgeBase.load(KB_FILES[:1])):
        assert files.etag == files_etag and rows(files, AISLE_OF_ROBOT1) == files_rows
        assert rows(files, PREFIX + "SELECT ?r WHERE { loc:Robot42 ?p ?r }") == set()
    # A second live KB over the same loaded files starts from the files too.
    assert rows(LiveKB(base, "B.1", wall_ms=Clock()), AISLE_OF_ROBOT1) == files_rows


def test_a_view_churned_by_writes_is_copied_afresh_and_answers_alike(tmp_path: Path) -> None:
    """pyoxigraph's in-memory store keeps memory for every value it ever
    held: after ``rebuild_after_changes`` adds and removes (or four times its
    size) the view is copied, and answers as one never copied (a long
    shift's positions grew a robot by 2.7 MiB a thousand jobs without it)."""
    ns = "http://www.tcs.org/2018/Location#"
    files = [tmp_path / "Location.ttl"]
    files[0].write_text(f"<{ns}Robot1> <{ns}Robot_aisle_no> 1 .\n<{ns}Shelf1> <{ns}Inventory_aisle_no> 2 .\n")
    copied = LiveKB(KnowledgeBase.load(files), "A.1", wall_ms=Clock(), limits=WriteLimits(rebuild_after_changes=50))
    kept = LiveKB(KnowledgeBase.load(files), "A.1", wall_ms=Clock())
    for n in range(1, 120):  # each write of a single value removes the one before
        for kb in (copied, kept):
            kb.update(f"PREFIX loc: <{ns}> INSERT DATA {{ loc:Robot1 loc:Robot_aisle_no {n % 9 + 1} ; "
                      f"loc:Robot_updated_ms {n} }}")
    assert copied.rebuilds >= 2 and kept.rebuilds == 0
    everything = "SELECT ?s ?p ?o WHERE { ?s ?p ?o }"
    assert rows(copied, everything) == rows(kept, everything) and copied.triple_count == kept.triple_count
