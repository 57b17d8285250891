"""Result sizes and codec costs: SPARQL-JSON vs CBOR-of-JSON vs compact CBOR.

Usage::

    .venv/bin/python -m experiments.codec_sizes [--backend oxigraph|rdflib] [--synthetic]

Answers come from the warehouse KB (``ontologies/Object.owl`` through
``coapkb.kb.store``) when it is there, else from synthetic results of
the same shape.  Prints a table and writes ``experiments/results/codec_sizes.csv``.

Columns:

* ``json``: SPARQL 1.1 Query Results JSON as ``coapkb.wire.codec.encode_json``
  writes it (no whitespace; rdflib's serialiser adds ~10 %).
* ``cbor(json)``: the same JSON document encoded as CBOR (cbor2).
* ``anchor``: the layout measured in docs/reports/2026-11-22-performance-anchors.md section 3,
  ``[vars, prefixes, rows]`` with prefixes from the query's PREFIX lines,
  IRIs as ``[index, local]`` and native literals, rebuilt here so the 955 B
  reference can be compared on the same answer.
* ``compact``: ``coapkb.wire.codec.encode_cbor`` (content-format 60).
* ``+zlib``: compact CBOR deflated (level 6), for reference only.

Timings are process CPU time per call: the best of 7 repeats of a loop
(least disturbed by other processes), and the median in brackets.
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import statistics
import sys
import time
import timeit
import zlib
from collections.abc import Callable, Sequence
from pathlib import Path

import cbor2
from rdflib.term import Literal, URIRef

from coapkb.model.results import AskResult, GraphResult, QueryResult, SelectResult
from coapkb.wire.codec import decode_cbor, decode_json, encode_cbor, encode_json

ROOT = Path(__file__).resolve().parent.parent

OBJ = "http://www.tcs.org/2018/Object#"
XSD = "http://www.w3.org/2001/XMLSchema#"
PREFIX = f"PREFIX ns_2: <{OBJ}>\n"

#: (label, SPARQL).  Query_3 as in the seed paper (6 variables) and as the
#: named query ``object-features`` (plus ?weight); 20-row answers in the
#: 7-variable shape of a product's full record and in a 3-variable shape whose JSON is the
#: size of the Q20 of docs/reports/2026-11-22-performance-anchors.md (about 5 KB).
QUERIES: tuple[tuple[str, str], ...] = (
    (
        "Q3 paper (1 row, 6 vars)",
        PREFIX
        + """SELECT ?frag ?price ?color ?shape ?dim ?grip WHERE {
  ns_2:Gucci_bag_14 ns_2:Item_fragility ?frag ; ns_2:price ?price ; ns_2:colour ?color ;
                    ns_2:has_shape ?shape ; ns_2:can_be_picked_by ?grip .
  ?shape ns_2:Item_dimension ?dim . }""",
    ),
    (
        "Q3 object-features (1 row, 7 vars)",
        PREFIX
        + """SELECT ?frag ?price ?color ?shape ?dim ?grip ?weight WHERE {
  ns_2:Gucci_bag_14 ns_2:Item_fragility ?frag ; ns_2:price ?price ; ns_2:colour ?color ;
                    ns_2:has_shape ?shape ; ns_2:can_be_picked_by ?grip ; ns_2:weight ?weight .
  ?shape ns_2:Item_dimension ?dim . }""",
    ),
    (
        "Q20 products (20 rows, 7 vars)",
        PREFIX
        + """SELECT ?product ?name ?price ?colour ?weight ?fragile ?shape WHERE {
  ?product ns_2:Product_name ?name ; ns_2:price ?price ; ns_2:colour ?colour ;
           ns_2:weight ?weight ; ns_2:Item_fragility ?fragile ; ns_2:has_shape ?shape .
} ORDER BY ?name LIMIT 20""",
    ),
    (
        "Q20 narrow (20 rows, 3 vars)",
        PREFIX
        + """SELECT ?product ?name ?price WHERE {
  ?product ns_2:Product_name ?name ; ns_2:price ?price .
} ORDER BY ?name LIMIT 20""",
    ),
    ("ASK", PREFIX + "ASK { ns_2:Gucci_bag_14 ns_2:Item_fragility true }"),
    ("DESCRIBE Gucci_bag_14 (graph)", PREFIX + "DESCRIBE ns_2:Gucci_bag_14"),
)


# --------------------------------------------------------------------------
# Answers


def kb_answers(backend: str) -> list[tuple[str, str, QueryResult]] | None:
    """The answers from the real KB, or None when it is not available."""
    owl = ROOT / "ontologies" / "Object.owl"
    try:
        from coapkb.kb.store import KnowledgeBase
    except ImportError:
        return None
    if not owl.exists():
        return None
    kb = KnowledgeBase.load([owl], backend=backend)
    answers = []
    for label, query in QUERIES:
        try:
            answers.append((label, query, kb.query(query)))
        except Exception as exc:  # noqa: BLE001 (a backend without DESCRIBE, say: report, go on)
            print(f"skipping {label}: {exc}", file=sys.stderr)
    return answers


def synthetic_answers() -> list[tuple[str, str, QueryResult]]:
    """Results shaped like the warehouse KB's (names average 17 characters)."""
    kinds = ["Barilla_pasta", "Levis_jeans", "Prada_bag", "Coach_sunglasses", "Kelloggs_olive_oil", "Gucci_bag"]
    colours = ["silver", "grey", "brown", "red", "navy", "blue", "purple", "gold", "white", "pink", "green", "black"]

    def dec(text: str) -> Literal:
        return Literal(text, datatype=URIRef(XSD + "decimal"))

    def boolean(value: bool) -> Literal:
        return Literal("true" if value else "false", datatype=URIRef(XSD + "boolean"))

    rows = []
    for i in range(20):
        name = f"{kinds[i % len(kinds)]}_{37 * i + 14}"
        rows.append(
            (
                URIRef(OBJ + name),
                Literal(name),
                dec(f"{(97 * i) % 900 + 5}.{(13 * i) % 100:02d}"),
                Literal(colours[(5 * i) % len(colours)]),
                dec(f"{i % 4}.{(7 * i) % 9 + 1}"),
                boolean(i % 4 == 0),
                URIRef(OBJ + "Shape_" + name),
            )
        )
    q3 = (
        boolean(False),
        dec("325.54"),
        Literal("black"),
        URIRef(OBJ + "Shape_Gucci_bag_14"),
        Literal("27x13x32 cm"),
        URIRef(OBJ + "gripping"),
    )
    gucci = URIRef(OBJ + "Gucci_bag_14")
    features = [
        ("Product_name", Literal("Gucci_bag_14")),
        ("Item_fragility", boolean(False)),
        ("price", dec("325.54")),
        ("colour", Literal("black")),
        ("weight", dec("0.8")),
        ("has_shape", URIRef(OBJ + "Shape_Gucci_bag_14")),
        ("can_be_picked_by", URIRef(OBJ + "gripping")),
    ]
    graph = GraphResult(tuple((gucci, URIRef(OBJ + p), o) for p, o in features))
    q3_vars = ("frag", "price", "color", "shape", "dim", "grip")
    product_vars = ("product", "name", "price", "colour", "weight", "fragile", "shape")
    results: list[QueryResult] = [
        SelectResult(q3_vars, (q3,)),
        SelectResult((*q3_vars, "weight"), ((*q3, dec("0.8")),)),
        SelectResult(product_vars, tuple(rows)),
        SelectResult(product_vars[:3], tuple(r[:3] for r in rows)),
        AskResult(True),
        graph,
    ]
    return [(label, query, result) for (label, query), result in zip(QUERIES, results, strict=True)]


# --------------------------------------------------------------------------
# The layout of docs/reports/2026-11-22-performance-anchors.md section 3, for comparison


def anchor_layout(result: QueryResult, query: str) -> bytes:
    """``[vars, prefixes, rows]``, prefixes from the query's PREFIX lines.

    As described in docs/reports/2026-11-22-performance-anchors.md section 3 (not lossless for every term:
    it was a size experiment): IRIs under a declared prefix as ``[index,
    local]``, other IRIs as text, decimals as tag 4, numbers and booleans
    native, other literals as their text.
    """
    if isinstance(result, AskResult):
        return cbor2.dumps(result.value)
    prefixes = re.findall(r"PREFIX\s+\w*:\s*<([^>]*)>", query)

    def term(t: object) -> object:
        if t is None:
            return None
        if isinstance(t, URIRef):
            for i, p in enumerate(prefixes):
                if t.startswith(p):
                    return [i, str(t)[len(p) :]]
            return str(t)
        if isinstance(t, Literal) and t.datatype is not None:
            value = t.toPython()
            if isinstance(value, (bool, int, float)):
                return value
            dt = str(t.datatype)
            if dt == XSD + "decimal":
                sign, digits, exponent = value.as_tuple()
                mantissa = int("".join(map(str, digits))) * (-1 if sign else 1)
                return cbor2.CBORTag(4, [exponent, mantissa])
        return str(t)

    rows: Sequence[Sequence[object]] = result.rows if isinstance(result, SelectResult) else result.triples
    head = list(result.variables) if isinstance(result, SelectResult) else None
    return cbor2.dumps([head, prefixes, [[term(t) for t in row] for row in rows]])


# --------------------------------------------------------------------------
# Measurement


def per_call_us(fn: Callable[[], object], budget_s: float = 0.3) -> tuple[float, float]:
    """(best, median) CPU microseconds per call over 7 repeats.

    Process CPU time rather than wall-clock time: the VM is shared, and time
    spent descheduled is not the codec's cost.
    """
    timer = timeit.Timer(fn, timer=time.process_time)
    number = max(1, int(budget_s / 7 / max(timer.timeit(number=3) / 3, 1e-7)))
    times = [t / number * 1e6 for t in timer.repeat(number=number, repeat=7)]
    return min(times), statistics.median(times)


def measure(label: str, query: str, result: QueryResult) -> dict[str, object]:
    compact = encode_cbor(result)
    sparql_json = encode_json(result)
    assert decode_cbor(compact) == result and decode_json(sparql_json) == result, label
    rows = len(result.rows) if isinstance(result, SelectResult) else len(getattr(result, "triples", ()))
    enc = per_call_us(lambda: encode_cbor(result))
    dec = per_call_us(lambda: decode_cbor(compact))
    enc_json = per_call_us(lambda: encode_json(result))
    dec_json = per_call_us(lambda: decode_json(sparql_json))
    return {
        "answer": label,
        "rows": rows,
        "vars": len(result.variables) if isinstance(result, SelectResult) else "",
        "sparql_json_B": len(sparql_json),
        "cbor_of_json_B": len(cbor2.dumps(json.loads(sparql_json))),
        "anchor_layout_B": len(anchor_layout(result, query)),
        "compact_cbor_B": len(compact),
        "compact_zlib6_B": len(zlib.compress(compact, 6)),
        "stringref": compact[:3] == b"\xd9\x01\x00",
        "encode_cbor_us": round(enc[0], 1),
        "encode_cbor_us_median": round(enc[1], 1),
        "decode_cbor_us": round(dec[0], 1),
        "encode_json_us": round(enc_json[0], 1),
        "decode_json_us": round(dec_json[0], 1),
    }


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m experiments.codec_sizes", description=__doc__.split("\n\n")[0])
    parser.add_argument("--backend", default="oxigraph", choices=("oxigraph", "rdflib"))
    parser.add_argument("--synthetic", action="store_true", help="use synthetic answers even if the KB is there")
    parser.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "codec_sizes.csv")
    args = parser.parse_args(argv)

    answers = None if args.synthetic else kb_answers(args.backend)
    source = f"KB ontologies/Object.owl ({args.backend})" if answers else "synthetic answers"
    answers = answers or synthetic_answers()
    table = [measure(*answer) for answer in answers]

    print(f"source: {source}")
    header = ("answer", "json", "cbor(json)", "anchor", "compact", "+zlib", "enc us", "dec us", "json enc/dec us")
    widths = (34, 6, 10, 7, 8, 6, 14, 7, 16)
    print(" ".join(f"{h:{'<' if i == 0 else '>'}{w}}" for i, (h, w) in enumerate(zip(header, widths, strict=True))))
    for r in table:
        print(
            f"{r['answer']:34} {r['sparql_json_B']:>6} {r['cbor_of_json_B']:>10} {r['anchor_layout_B']:>7} "
            f"{r['compact_cbor_B']:>8} {r['compact_zlib6_B']:>6} "
            f"{r['encode_cbor_us']:>6} ({r['encode_cbor_us_median']:>5}) {r['decode_cbor_us']:>7} "
            f"{r['encode_json_us']:>7}/{r['decode_json_us']:<8}"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with args.out.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(table[0]))
        writer.writeheader()
        writer.writerows(table)
    print(f"wrote {args.out.relative_to(ROOT) if args.out.is_relative_to(ROOT) else args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
