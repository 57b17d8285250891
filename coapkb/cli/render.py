"""A query result as text: an aligned table, SPARQL 1.1 JSON or CSV (pure)."""

from __future__ import annotations

import csv
import io
import json
from typing import TYPE_CHECKING, Any

from ..wire import codec
from ..world import CAPABILITY_NS, LOCATION_NS, OBJECT_NS

if TYPE_CHECKING:
    from ..model.results import QueryResult

WELL_KNOWN_PREFIXES = {
    "obj": OBJECT_NS,
    "loc": LOCATION_NS,
    "cap": CAPABILITY_NS,
    "rdf": "http://www.w3.org/1999/02/22-rdf-syntax-ns#",
    "rdfs": "http://www.w3.org/2000/01/rdf-schema#",
    "owl": "http://www.w3.org/2002/07/owl#",
    "xsd": "http://www.w3.org/2001/XMLSchema#",
}


def render(result: QueryResult, fmt: str) -> str:
    """A query result as text: an aligned table, SPARQL-JSON, or SPARQL CSV."""
    from ..model.results import AskResult, GraphResult, SelectResult

    if fmt == "json":
        return json.dumps(json.loads(codec.encode_json(result)), indent=2) + "\n"
    if isinstance(result, AskResult):
        return ("true" if result.value else "false") + "\n"
    if isinstance(result, GraphResult):
        rows: list[list[Any]]
        header, rows = ["subject", "predicate", "object"], [list(t) for t in result.triples]
    else:
        assert isinstance(result, SelectResult)
        header, rows = list(result.variables), [list(r) for r in result.rows]
    if fmt == "csv":
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\r\n")  # SPARQL 1.1 CSV uses CRLF
        writer.writerow(header)
        writer.writerows([["" if t is None else str(t) for t in row] for row in rows])
        return out.getvalue()
    cells = [[_short(t) for t in row] for row in rows]
    widths = [max([len(h)] + [len(r[i]) for r in cells]) for i, h in enumerate(header)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(header, widths)).rstrip()]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip() for row in cells]
    truncated = getattr(result, "truncated", False)
    cut = ", truncated by the server; coapkb dump URI --module NAME reads a whole module" if truncated else ""
    lines.append(f"({len(rows)} row{'s' if len(rows) != 1 else ''}{cut})")
    return "\n".join(lines) + "\n"


def _short(term: object) -> str:
    from rdflib.term import BNode, Literal, URIRef

    if term is None:
        return ""
    if isinstance(term, URIRef):
        for prefix, ns in WELL_KNOWN_PREFIXES.items():
            if term.startswith(ns):
                return f"{prefix}:{term[len(ns):]}"
        return f"<{term}>"
    if isinstance(term, BNode):
        return f"_:{term}"
    assert isinstance(term, Literal)
    return str(term) + (f"@{term.language}" if term.language else "")
