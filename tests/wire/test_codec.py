"""Property and example tests of the result codecs (coapkb/wire/codec.py).

* Round trips are exact, down to lexical form, datatype and language tag
  (rdflib's ``==`` compares language tags case-insensitively, so
  :func:`assert_same` checks every field itself).
* Both codecs agree: ``decode_cbor(encode_cbor(r)) == decode_json(encode_json(r))``.
* Decoders raise nothing but ``CodecError`` on arbitrary or mutated bytes.
* Encoded samples validate against docs/compact-results.cddl with an
  independent CDDL validator (``cddl-verifier``), so spec and code cannot
  drift apart.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Iterator
from decimal import Decimal
from types import SimpleNamespace

import cbor2
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from rdflib.term import BNode, Literal, URIRef
from support import ROOT, require

from coapkb.model.results import AskResult, GraphResult, QueryResult, SelectResult
from coapkb.wire.codec import (
    GRAPH_VARS,
    MAX_PREFIX_TABLE_CHARS,
    WELL_KNOWN_DATATYPES,
    CodecError,
    decode_cbor,
    decode_json,
    encode_cbor,
    encode_json,
    render_decimal,
    render_double,
)

# rdflib's XSD/RDF namespace objects warn when pytest inspects module globals.
_X = "http://www.w3.org/2001/XMLSchema#"
_R = "http://www.w3.org/1999/02/22-rdf-syntax-ns#"
_XSD_USED = ["string", "boolean", "decimal", "integer", "double", "float", "dateTime", "date", "gYear", "int"]
XSD = SimpleNamespace(**{name: URIRef(_X + name) for name in _XSD_USED})
RDF = SimpleNamespace(**{name: URIRef(_R + name) for name in ["HTML", "XMLLiteral", "langString"]})

CDDL = ROOT / "docs" / "compact-results.cddl"
OBJ = "http://www.tcs.org/2018/Object#"
LOC = "http://www.tcs.org/2018/Location#"


# rdflib warns about the ill-typed literals the generators make on purpose.
pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


@pytest.fixture(autouse=True)
def _quiet_rdflib() -> Iterator[None]:
    """rdflib logs a warning with a traceback for every ill-typed literal
    (``"abc"^^xsd:integer``), which the generators produce on purpose."""
    logger = logging.getLogger("rdflib.term")
    level = logger.level
    logger.setLevel(logging.CRITICAL)
    yield
    logger.setLevel(level)


# --------------------------------------------------------------------------
# Exact comparison


def term_key(term: object) -> tuple[object, ...]:
    if term is None:
        return (None,)
    if isinstance(term, Literal):
        return (type(term), str(term), term.datatype, term.language)
    return (type(term), str(term))


def result_key(result: QueryResult) -> tuple[object, ...]:
    if isinstance(result, AskResult):
        return ("ask", result.value)
    if isinstance(result, SelectResult):
        return ("select", result.variables, tuple(tuple(map(term_key, r)) for r in result.rows), result.truncated)
    return ("graph", tuple(tuple(map(term_key, t)) for t in result.triples), result.truncated)


def assert_same(decoded: QueryResult, original: QueryResult) -> None:
    assert decoded == original
    assert result_key(decoded) == result_key(original)


# --------------------------------------------------------------------------
# Generators

# Namespaces ending in '#' or '/', one ending in neither, one IRI scheme with
# no separator at all, and the empty string (the IRI is all local name).
NAMESPACES = [OBJ, LOC, "http://example.org/a/b/", "http://example.org/x#y/", "urn:isbn:", "", "tag:robot,2024:"]
local_names = st.text(alphabet=st.sampled_from("abcXYZ_019-.:#/é中 "), min_size=0, max_size=12) | st.sampled_from(
    ["Gucci_bag_14", "Shape_Gucci_bag_14", "gripping", ""]
)
iris = st.builds(lambda ns, local: URIRef(ns + local), st.sampled_from(NAMESPACES), local_names) | st.builds(
    URIRef, st.text(max_size=20)
)
bnodes = st.builds(BNode, st.text(max_size=12) | st.sampled_from(["b0", "N3a1f", "genid-1"]))
language_tags = st.from_regex(r"[a-zA-Z]{1,8}(-[a-zA-Z0-9]{1,8}){0,2}", fullmatch=True)

# Lexical forms that are canonical, non-canonical and ill-typed, per datatype.
integer_lexicals = st.one_of(
    st.integers().map(str),
    st.integers(min_value=2**64 - 3, max_value=2**70).map(str),
    st.sampled_from(["01", "-0", "+5", "0", "-1", " 1", "1_0", "١٢", "18446744073709551615", "-18446744073709551616"]),
)
decimal_lexicals = st.one_of(
    st.decimals(allow_nan=False, allow_infinity=False).map(lambda d: format(d, "f")),
    st.builds(lambda i, f: f"{i}.{f}", st.integers(-(10**6), 10**6), st.text("0123456789", min_size=1, max_size=6)),
    st.sampled_from(["1.50", "-0.0", "0.05", ".5", "5.", "+1.5", "007.5", "129.99", "-0", "1E2", "0.0", "1" * 25]),
)
double_lexicals = st.one_of(
    st.floats().map(repr),
    st.floats(allow_nan=False).map(lambda f: format(f, ".17g")),
    st.sampled_from(["1E0", "1.0", "2", "NaN", "INF", "-INF", "nan", "inf", "-0.0", "0.0", "1e+16", "1e16", "1.5e-07"]),
)
boolean_lexicals = st.sampled_from(["true", "false", "1", "0", "TRUE", " true"])
OTHER_DATATYPES = [XSD.string, XSD.float, XSD.dateTime, XSD.date, XSD.gYear, XSD.int, RDF.HTML, RDF.langString]
CUSTOM_DATATYPES = [URIRef(OBJ + "Money"), URIRef("urn:dt:kg"), URIRef("http://example.org/dt/unit")]

typed_literals = st.one_of(
    st.builds(lambda lex: Literal(lex, datatype=XSD.integer, normalize=False), integer_lexicals | st.text()),
    st.builds(lambda lex: Literal(lex, datatype=XSD.decimal, normalize=False), decimal_lexicals | st.text()),
    st.builds(lambda lex: Literal(lex, datatype=XSD.double, normalize=False), double_lexicals | st.text()),
    st.builds(lambda lex: Literal(lex, datatype=XSD.boolean, normalize=False), boolean_lexicals | st.text()),
    st.builds(
        lambda lex, dt: Literal(lex, datatype=dt, normalize=False),
        st.text(max_size=20),
        st.sampled_from(OTHER_DATATYPES + CUSTOM_DATATYPES) | iris,
    ),
)
# Literals made from Python values go through rdflib's own normalisation.
python_literals = st.builds(
    Literal,
    st.one_of(
        st.integers(),
        st.floats(),
        st.booleans(),
        st.decimals(allow_nan=False, allow_infinity=False, places=3),
    ),
)
literals = st.one_of(
    st.builds(Literal, st.text(max_size=20)),
    st.builds(lambda lex, lang: Literal(lex, lang=lang), st.text(max_size=10), language_tags),
    typed_literals,
    python_literals,
)
terms = st.one_of(iris, bnodes, literals)


@st.composite
def select_results(draw: st.DrawFn) -> SelectResult:
    variables = draw(st.lists(st.text(min_size=1, max_size=8), unique=True, max_size=6))
    width = len(variables)
    value = st.none() | terms
    rows = draw(st.lists(st.tuples(*[value] * width), max_size=8))
    return SelectResult(tuple(variables), tuple(rows), draw(st.booleans()))


@st.composite
def graph_results(draw: st.DrawFn) -> GraphResult:
    triple = st.tuples(iris | bnodes, iris, terms)
    return GraphResult(tuple(draw(st.lists(triple, max_size=8))), draw(st.booleans()))


results = st.one_of(select_results(), graph_results(), st.builds(AskResult, st.booleans()))


# --------------------------------------------------------------------------
# Warehouse-shaped answers (the size targets)


BRAND_KINDS = ["Barilla_pasta", "Levis_jeans", "Prada_bag", "Coach_sunglasses", "Kelloggs_olive_oil", "Gucci_bag"]
COLOURS = ["silver", "grey", "brown", "red", "navy", "blue", "purple", "gold", "white", "pink", "green", "black"]


def warehouse_row(i: int) -> tuple[URIRef, Literal, Literal, Literal, Literal, Literal, URIRef]:
    """A product row like coapkb.world.generator's (names average 17 characters there)."""
    name = f"{BRAND_KINDS[i % len(BRAND_KINDS)]}_{37 * i + 14}"
    return (
        URIRef(OBJ + name),
        Literal(name),
        Literal(f"{(97 * i) % 900 + 5}.{(13 * i) % 100:02d}", datatype=XSD.decimal),
        Literal(COLOURS[(5 * i) % len(COLOURS)]),
        Literal(f"{i % 4}.{(7 * i) % 9 + 1}{'' if i % 3 else i % 7}", datatype=XSD.decimal),
        Literal(["false", "true"][i % 4 == 0], datatype=XSD.boolean),
        URIRef(OBJ + "Shape_" + name),
    )


WAREHOUSE_VARS = ("product", "name", "price", "colour", "weight", "fragile", "shape")
WAREHOUSE_20 = SelectResult(WAREHOUSE_VARS, tuple(warehouse_row(i) for i in range(20)))
QUERY_3 = SelectResult(
    ("frag", "price", "color", "shape", "dim", "grip"),
    (
        (
            Literal("false", datatype=XSD.boolean),
            Literal("325.54", datatype=XSD.decimal),
            Literal("black"),
            URIRef(OBJ + "Shape_Gucci_bag_14"),
            Literal("27x13x32 cm"),
            URIRef(OBJ + "gripping"),
        ),
    ),
)


# --------------------------------------------------------------------------
# Round-trip properties

SETTINGS = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@SETTINGS
@given(results)
@example(WAREHOUSE_20)
@example(QUERY_3)
@example(SelectResult((), ((),), False))
@example(GraphResult((), True))
def test_cbor_round_trip_is_exact(result: QueryResult) -> None:
    data = encode_cbor(result)
    assert_same(decode_cbor(data), result)
    assert encode_cbor(result) == data  # deterministic


@SETTINGS
@given(results)
@example(WAREHOUSE_20)
def test_json_round_trip_is_exact(result: QueryResult) -> None:
    data = encode_json(result)
    assert_same(decode_json(data), result)


@SETTINGS
@given(results)
def test_cbor_and_json_agree(result: QueryResult) -> None:
    from_cbor = decode_cbor(encode_cbor(result))
    from_json = decode_json(encode_json(result))
    assert result_key(from_cbor) == result_key(from_json)


@SETTINGS
@given(results)
def test_cbor_is_valid_cbor_for_other_decoders(result: QueryResult) -> None:
    """cbor2's generic decoder (with stringref support) reads every payload,
    and the result has the documented top-level shape."""
    item = cbor2.loads(encode_cbor(result))
    if isinstance(result, AskResult):
        assert item is result.value
    else:
        assert isinstance(item, list) and len(item) == (4 if result.truncated else 3)


# --------------------------------------------------------------------------
# Fuzzing: only CodecError, ever


def _decode_or_codec_error(decode: object, data: bytes) -> None:
    try:
        result = decode(data)  # type: ignore[operator]
    except CodecError as exc:
        assert str(exc)
    else:
        assert isinstance(result, (SelectResult, AskResult, GraphResult))


@settings(max_examples=1500, deadline=None)
@given(st.binary(max_size=200))
@example(b"")
@example(b"\xd9\x01\x00\x83\x80\x80\x81\x81\xd8\x19\x00")  # stringref to nothing
@example(b"\x83\x80\x81\x61a\x81\x82\x05\x61x")  # prefix index out of range
@example(b"\x83\x80\x80\x81\x81\xc4\x82\x01\x05")  # decimal with a positive exponent
@example(b"\x9b\x00\x00\x00\x10\x00\x00\x00\x00")  # huge array length
@example(b"\x81" * 5000)  # deep nesting
def test_decode_cbor_fuzz_raises_only_codec_error(data: bytes) -> None:
    _decode_or_codec_error(decode_cbor, data)


@settings(max_examples=1500, deadline=None)
@given(st.binary(max_size=200))
@example(b"[" * 100_000)
@example(b'{"head":{"vars":["a"]},"results":{"bindings":[{"a":{"type":"uri","value":"\\ud800"}}]}}')
@example(b'{"head":{},"boolean":1}')
def test_decode_json_fuzz_raises_only_codec_error(data: bytes) -> None:
    _decode_or_codec_error(decode_json, data)


JSON_KEYS = ["head", "vars", "results", "bindings", "boolean", "type", "value", "xml:lang", "datatype"]
JSON_KEYS += ["a", "graph", "truncated", "subject", "predicate", "object"]
json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.text(max_size=5) | st.sampled_from(["uri", "literal", "bnode"]),
    lambda children: (
        st.lists(children, max_size=3)
        | st.dictionaries(
            st.sampled_from(JSON_KEYS),
            children,
            max_size=4,
        )
    ),
    max_leaves=20,
)


@settings(max_examples=1000, deadline=None)
@given(json_values)
def test_decode_json_structured_fuzz(value: object) -> None:
    _decode_or_codec_error(decode_json, json.dumps(value).encode())


@settings(max_examples=500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(results, st.data())
def test_decode_mutated_cbor_raises_only_codec_error(result: QueryResult, data: st.DataObject) -> None:
    """Flip, drop and truncate bytes of valid payloads: reaches the deep paths."""
    payload = bytearray(encode_cbor(result))
    for _ in range(data.draw(st.integers(1, 4))):
        op = data.draw(st.sampled_from(["flip", "drop", "insert", "truncate"]))
        pos = data.draw(st.integers(0, max(len(payload) - 1, 0)))
        if op == "flip" and payload:
            payload[pos] ^= 1 << data.draw(st.integers(0, 7))
        elif op == "drop" and payload:
            del payload[pos]
        elif op == "insert":
            payload.insert(pos, data.draw(st.integers(0, 255)))
        else:
            del payload[pos:]
    _decode_or_codec_error(decode_cbor, bytes(payload))


@settings(max_examples=300, deadline=None)
@given(results, st.data())
def test_decode_mutated_json_raises_only_codec_error(result: QueryResult, data: st.DataObject) -> None:
    payload = bytearray(encode_json(result))
    pos = data.draw(st.integers(0, len(payload) - 1))
    payload[pos] = data.draw(st.integers(0, 255))
    _decode_or_codec_error(decode_json, bytes(payload))


# --------------------------------------------------------------------------
# The specification: CDDL, examples, lexical rules


@pytest.fixture(scope="module")
def cddl() -> object:
    try:
        import cddl_verifier
    except ImportError:
        require(False, "cddl-verifier is not installed (a test dependency in pyproject.toml)")
    return cddl_verifier.Validator(CDDL)


def assert_valid(cddl: object, data: bytes) -> None:
    outcome = cddl.validate(data, root_type="compact-results")  # type: ignore[attr-defined]
    assert outcome.valid, [str(d) for d in outcome.diagnostics]


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(results)
@example(WAREHOUSE_20)
@example(QUERY_3)
def test_encoded_samples_match_the_cddl(cddl: object, result: QueryResult) -> None:
    assert_valid(cddl, encode_cbor(result))


@pytest.mark.parametrize(
    "item",
    [
        [["a"], [], [[None]], False],  # truncated must be true when present
        [["a"], [], [[cbor2.undefined]]],
        [["a"], [], [[cbor2.CBORTag(4, [1, 5])]]],  # positive exponent
        [["a"], [], [[["x", 41]]]],  # datatype code out of range
        [["a"], [], [[2**70]]],  # bignum
        [["a"], [], [[cbor2.CBORTag(25, 0)]]],  # stringref outside tag 256
        [None, [], [[["b"], ["p"], "o"]]],  # blank-node predicate
        [["a"], [b"x"], []],  # byte-string prefix
    ],
)
def test_cddl_and_decoder_both_reject(cddl: object, item: object) -> None:
    data = cbor2.dumps(item)
    assert not cddl.validate(data, root_type="compact-results").valid  # type: ignore[attr-defined]
    with pytest.raises(CodecError):
        decode_cbor(data)


def diag(result: QueryResult) -> object:
    """The generic CBOR data model of an encoding, Decimal for tag 4."""
    return cbor2.loads(encode_cbor(result))


def test_examples_from_the_docs() -> None:
    assert encode_cbor(AskResult(True)) == b"\xf5"
    assert diag(QUERY_3) == [
        ["frag", "price", "color", "shape", "dim", "grip"],
        [OBJ],
        [[False, Decimal("325.54"), "black", [0, "Shape_Gucci_bag_14"], "27x13x32 cm", [0, "gripping"]]],
    ]
    assert encode_cbor(QUERY_3).hex().startswith("8386")  # array(3), vars array(6)
    row = SelectResult(
        ("x",),
        (
            (Literal("01", datatype=XSD.integer, normalize=False),),
            (Literal("chat", lang="fr"),),
            (Literal("2024-05-01", datatype=XSD.date),),
            (Literal("9.5", datatype=URIRef(OBJ + "kg")),),
            (BNode("b0"),),
            (None,),
            (URIRef("urn:isbn:0451450523"),),
        ),
        truncated=True,
    )
    # One use of the tcs.org namespace does not pay for an entry: both IRIs
    # travel whole through the "" entry.
    assert diag(row) == [
        ["x"],
        [""],
        [
            [["01", 3]],  # not canonical: lexical form + xsd:integer's code
            [["chat", "fr"]],
            [["2024-05-01", 6]],  # xsd:date
            [["9.5", 0, OBJ + "kg"]],  # custom datatype through the prefix table
            [["b0"]],
            [None],
            [[0, "urn:isbn:0451450523"]],
        ],
        True,
    ]


def test_prefix_table_only_when_it_pays_off() -> None:
    one = SelectResult(("s",), ((URIRef(OBJ + "a"),),))
    assert diag(one) == [["s"], [""], [[[0, OBJ + "a"]]]]
    two = SelectResult(("s",), ((URIRef(OBJ + "a"),), (URIRef(OBJ + "b"),)))
    assert diag(two) == [["s"], [OBJ], [[[0, "a"]], [[0, "b"]]]]


def test_suffix_split_and_relative_prefix_entry() -> None:
    """``Shape_X`` next to ``X``: the prefix grows to ``...#Shape_`` (sent as
    an extension of ``...#``) and the local name becomes a stringref."""
    data = encode_cbor(WAREHOUSE_20)
    assert data[:3] == b"\xd9\x01\x00"  # tag 256: stringrefs pay off
    item = cbor2.loads(data)
    assert item[1] == [OBJ, [0, "Shape_"]]
    assert item[2][0][6] == [1, item[2][0][0][1]]
    name = str(WAREHOUSE_20.rows[0][1]).encode()
    assert data.count(name) == 1  # product local name sent once; name and shape refer to it


def test_prefix_table_stays_within_the_decoders_limit() -> None:
    """Hundreds of long namespaces: the encoder drops entries rather than
    exceed MAX_PREFIX_TABLE_CHARS; the rest travel through the "" entry."""
    rows = tuple((URIRef(f"http://example.org/{'n' * 60}{i}/{j}"),) for i in range(200) for j in range(2))
    result = SelectResult(("s",), rows)
    assert 400 * 60 > MAX_PREFIX_TABLE_CHARS  # every namespace is used twice: all would pay off
    item = cbor2.loads(encode_cbor(result))
    assert "" in item[1]
    assert_same(decode_cbor(encode_cbor(result)), result)  # the decoder enforces the limit


def test_no_stringref_namespace_when_it_does_not_pay() -> None:
    assert encode_cbor(QUERY_3)[:1] == b"\x83"


@pytest.mark.parametrize(
    ("lexical", "datatype", "expected"),
    [
        ("42", XSD.integer, 42),
        ("-7", XSD.integer, -7),
        ("01", XSD.integer, ["01", 3]),
        ("-0", XSD.integer, ["-0", 3]),
        ("+5", XSD.integer, ["+5", 3]),
        ("18446744073709551616", XSD.integer, ["18446744073709551616", 3]),  # beyond 64 bits
        ("129.99", XSD.decimal, Decimal("129.99")),
        ("1.50", XSD.decimal, Decimal("1.50")),
        ("0.05", XSD.decimal, Decimal("0.05")),
        ("7", XSD.decimal, Decimal("7")),
        ("-0.0", XSD.decimal, ["-0.0", 2]),
        (".5", XSD.decimal, [".5", 2]),
        ("5.", XSD.decimal, ["5.", 2]),
        ("1.35", XSD.double, 1.35),
        ("2.0", XSD.double, 2.0),
        ("1e+16", XSD.double, 1e16),
        ("1E0", XSD.double, ["1E0", 4]),
        ("2", XSD.double, ["2", 4]),
        ("nan", XSD.double, ["nan", 4]),
        ("INF", XSD.double, math.inf),
        ("-INF", XSD.double, -math.inf),
        ("true", XSD.boolean, True),
        ("1", XSD.boolean, ["1", 1]),
        ("x", XSD.string, ["x", 0]),
        ("1.5", XSD.float, ["1.5", 5]),
    ],
)
def test_native_forms_only_when_lossless(lexical: str, datatype: URIRef, expected: object) -> None:
    result = SelectResult(("v",), ((Literal(lexical, datatype=datatype, normalize=False),),))
    value = diag(result)[2][0][0]  # type: ignore[index]
    assert value == expected and type(value) is type(expected)
    assert_same(decode_cbor(encode_cbor(result)), result)


def test_nan_round_trips() -> None:
    result = SelectResult(("v",), ((Literal("NaN", datatype=XSD.double, normalize=False),),))
    assert encode_cbor(result).endswith(b"\xf9\x7e\x00")
    assert_same(decode_cbor(encode_cbor(result)), result)


@given(st.floats())
def test_render_double_round_trips(value: float) -> None:
    text = render_double(value)
    assert math.isnan(value) or float(text) == value or text in ("INF", "-INF")


@given(st.integers(-1000, 0), st.integers(-(2**64), 2**64 - 1))
def test_render_decimal_is_exact(exponent: int, mantissa: int) -> None:
    assert Decimal(render_decimal(exponent, mantissa)) == Decimal(mantissa).scaleb(exponent)


def test_well_known_datatypes_are_stable() -> None:
    """The codes are part of the wire format (docs/compact-results.md)."""
    assert len(WELL_KNOWN_DATATYPES) == 41
    assert WELL_KNOWN_DATATYPES[:5] == tuple(
        str(d) for d in (XSD.string, XSD.boolean, XSD.decimal, XSD.integer, XSD.double)
    )
    assert WELL_KNOWN_DATATYPES[-2:] == (str(RDF.HTML), str(RDF.XMLLiteral))


def test_literal_slots_match_properties() -> None:
    """The encoder reads rdflib's ``_datatype``/``_language`` slots directly."""
    for literal in (Literal("a", lang="en"), Literal("1", datatype=XSD.integer), Literal("x")):
        assert literal._datatype == literal.datatype and literal._language == literal.language


# --------------------------------------------------------------------------
# Error messages


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"", "empty"),
        (encode_cbor(QUERY_3)[:-3], "malformed CBOR"),
        (encode_cbor(QUERY_3) + b"\x00", "trailing"),
        (cbor2.dumps([["a"], ["p"], [[[3, "x"]]]]), "prefix index 3 out of range"),
        (cbor2.dumps([["a"], [], [[1, 2]]]), "row 0 must be an array of 1"),
        (cbor2.dumps([["a", "a"], [], []]), "duplicate variable"),
        (cbor2.dumps([["a"], [[0, "x"]], []]), "not an earlier entry"),
        (cbor2.dumps({"a": 1}), "top level"),
        (cbor2.dumps([["a"], [], [[cbor2.CBORTag(1, 0)]]]), "tag 1"),
        (cbor2.dumps([["a"], [], [[["x", "not a tag"]]]]), "language tag"),
        (cbor2.dumps([["a"], ["x" * 100] + [[i, "x" * 100] for i in range(100)], []]), "prefix table exceeds"),
    ],
)
def test_cbor_errors_say_what_is_wrong(data: bytes, message: str) -> None:
    with pytest.raises(CodecError, match=message):
        decode_cbor(data)


def test_encode_refuses_what_it_cannot_carry() -> None:
    with pytest.raises(CodecError, match="duplicate variable"):
        encode_cbor(SelectResult(("a", "a"), ()))
    with pytest.raises(CodecError, match="subject"):
        encode_cbor(GraphResult(((Literal("x"), URIRef("urn:p"), Literal("o")),)))
    with pytest.raises(CodecError, match="not an RDF term"):
        encode_cbor(SelectResult(("a",), (("plain str",),)))  # type: ignore[arg-type]
    with pytest.raises(CodecError, match="UTF-8"):
        encode_cbor(SelectResult(("a",), ((Literal("\ud800"),),)))
    with pytest.raises(CodecError, match="UTF-8"):
        encode_json(SelectResult(("a",), ((Literal("\ud800"),),)))


# --------------------------------------------------------------------------
# SPARQL 1.1 Query Results JSON

# The example of the W3C Recommendation (section 3), minus "link".
W3C_EXAMPLE = b"""{
  "head": { "vars": [ "x", "hpage", "name", "mbox", "age", "blurb", "friend" ] },
  "results": { "bindings": [
      { "x" : { "type": "bnode", "value": "r1" },
        "hpage" : { "type": "uri", "value": "http://work.example.org/alice/" },
        "name" : {  "type": "literal", "value": "Alice" } ,
        "mbox" : {  "type": "literal", "value": "" } ,
        "blurb" : { "datatype": "http://www.w3.org/1999/02/22-rdf-syntax-ns#XMLLiteral", "type": "literal",
                    "value": "<p xmlns=\\"http://www.w3.org/1999/xhtml\\">My name is <b>alice</b></p>" },
        "friend" : { "type": "bnode", "value": "r2" } },
      { "x" : { "type": "bnode", "value": "r2" },
        "hpage" : { "type": "uri", "value": "http://work.example.org/bob/" },
        "name" : { "type": "literal", "value": "Bob", "xml:lang": "en" },
        "mbox" : { "type": "uri", "value": "mailto:bob@work.example.org" },
        "friend" : { "type": "bnode", "value": "r1" } }
  ] }
}"""


def test_decodes_the_w3c_example() -> None:
    result = decode_json(W3C_EXAMPLE)
    assert isinstance(result, SelectResult)
    assert result.variables == ("x", "hpage", "name", "mbox", "age", "blurb", "friend")
    alice, bob = result.rows
    assert alice[0] == BNode("r1") and alice[4] is None
    assert alice[5] == Literal('<p xmlns="http://www.w3.org/1999/xhtml">My name is <b>alice</b></p>',
                               datatype=RDF.XMLLiteral, normalize=False)  # fmt: skip
    assert bob[2] == Literal("Bob", lang="en") and bob[3] == URIRef("mailto:bob@work.example.org")
    assert_same(decode_json(encode_json(result)), result)
    assert_same(decode_cbor(encode_cbor(result)), result)


def test_json_matches_the_spec_shape() -> None:
    result = SelectResult(
        ("s", "o"),
        ((URIRef(OBJ + "a"), Literal("1.5", datatype=XSD.decimal)), (BNode("b"), None)),
        truncated=True,
    )
    assert json.loads(encode_json(result)) == {
        "head": {"vars": ["s", "o"]},
        "results": {
            "bindings": [
                {
                    "s": {"type": "uri", "value": OBJ + "a"},
                    "o": {"type": "literal", "value": "1.5", "datatype": str(XSD.decimal)},
                },
                {"s": {"type": "bnode", "value": "b"}},
            ]
        },
        "truncated": True,
    }
    assert json.loads(encode_json(AskResult(False))) == {"head": {}, "boolean": False}
    assert json.loads(encode_json(SelectResult(("l",), ((Literal("x", lang="en-GB"),),)))) == {
        "head": {"vars": ["l"]},
        "results": {"bindings": [{"l": {"type": "literal", "value": "x", "xml:lang": "en-GB"}}]},
    }


def test_json_graph_form() -> None:
    triple = (URIRef(OBJ + "Gucci_bag_14"), URIRef(OBJ + "colour"), Literal("black"))
    doc = json.loads(encode_json(GraphResult((triple,))))
    assert doc["head"] == {"vars": list(GRAPH_VARS)} and doc["graph"] is True
    assert doc["results"]["bindings"][0]["object"] == {"type": "literal", "value": "black"}
    # A SPARQL 1.0 "typed-literal" is read too.
    legacy = b'{"head":{"vars":["v"]},"results":{"bindings":[{"v":{"type":"typed-literal","value":"1","datatype":"http://www.w3.org/2001/XMLSchema#integer"}}]}}'
    assert decode_json(legacy) == SelectResult(("v",), ((Literal("1", datatype=XSD.integer),),))


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"\xff", "malformed JSON"),
        (b"[]", "must be an object"),
        (b'{"head":{"vars":["a"]},"results":{"bindings":[{"b":{"type":"uri","value":"x"}}]}}', "not in head.vars"),
        (b'{"head":{"vars":["a"]},"results":{"bindings":[{"a":{"type":"triple","value":"x"}}]}}', "unsupported"),
        (b'{"head":{"vars":["a"]},"results":{"bindings":[{"a":{"type":"uri"}}]}}', "lacks 'value'"),
        (b'{"head":{"vars":["a"]},"results":{"bindings":[]},"truncated":"yes"}', "'truncated' must be a bool"),
        (b'{"head":{"vars":["subject","predicate","object"]},"results":{"bindings":[{}]},"graph":true}', "unbound"),
        (b'{"head":{},"boolean":true,"results":{}}', "both"),
        (b'{"head":{"vars":["a"]},"results":{"bindings":[{"a":{"type":"uri","value":"\\udc00"}}]}}', "malformed JSON"),
    ],
)
def test_json_errors_say_what_is_wrong(data: bytes, message: str) -> None:
    with pytest.raises(CodecError, match=message):
        decode_json(data)


# --------------------------------------------------------------------------
# Size targets (docs/reports/2026-11-22-performance-anchors.md section 3)


def test_twenty_row_warehouse_answer_fits_one_datagram() -> None:
    """7 variables x 20 rows of the warehouse KB's shape: about 1 KB, within
    the 1,124 B aiocoap sends as one message (SPARQL JSON: about 11 KB).
    The 955 B anchor was a narrower answer: see test_anchor_sized_answer
    and docs/compact-results.md."""
    size = len(encode_cbor(WAREHOUSE_20))
    json_size = len(encode_json(WAREHOUSE_20))
    assert size <= 1124, size
    assert size * 10 < json_size


def test_anchor_sized_answer() -> None:
    """An answer of the anchor's size (SPARQL JSON about 5 KB for 20 rows:
    product, name, price) encodes well under the anchor's 955 B."""
    result = SelectResult(WAREHOUSE_VARS[:3], tuple(row[:3] for row in WAREHOUSE_20.rows))
    assert 4000 < len(encode_json(result)) < 6000
    assert len(encode_cbor(result)) < 700


def test_query_3_is_about_a_hundred_bytes() -> None:
    size = len(encode_cbor(QUERY_3))
    assert size <= 130, size  # 40 B of it are the variable names and the namespace
