"""The ``"rdflib"`` backend: a plain ``rdflib.Graph``, the seed paper's
library, with its prepared queries cached and its result terms normalised to
the ones Oxigraph returns."""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from decimal import Decimal
from pathlib import Path
from typing import Any, overload

import rdflib
from rdflib.plugins.sparql.sparql import Query as SparqlQuery
from rdflib.term import Literal, Node

from ..model.results import AskResult, GraphResult, QueryResult, SelectResult, Term
from .errors import KBError, KBLoadError, QueryEvaluationError, QuerySyntaxError, short_message
from .limits import Deadline, take
from .refusals import refuse_or_syntax

_XSD_STRING = "http://www.w3.org/2001/XMLSchema#string"
_UNKNOWN_PREFIX = re.compile(r"Unknown namespace prefix\s*:\s*(\S+)")


def _locate(text: str, needle_regex: str) -> tuple[int | None, int | None]:
    m = re.search(needle_regex, text)
    if m is None:
        return None, None
    line = text.count("\n", 0, m.start()) + 1
    column = m.start() - (text.rfind("\n", 0, m.start()) + 1) + 1
    return line, column


_XSD = "http://www.w3.org/2001/XMLSchema#"
_INTEGER_LEX = re.compile(r"[+-]?[0-9]+")
_DECIMAL_LEX = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)")
_I64 = 2**63


def _canonical_lexical(datatype: str, lexical: str) -> str | None:
    """The lexical form Oxigraph would return for a valid xsd:integer,
    xsd:decimal or xsd:boolean literal (it stores these as values, so
    ``"86.0"`` comes back as ``"86"``), or None to keep the literal as is.
    Out-of-range values, which Oxigraph keeps verbatim, are kept too."""
    if datatype == _XSD + "integer":
        if _INTEGER_LEX.fullmatch(lexical) and -_I64 <= (n := int(lexical)) < _I64:
            return str(n)
    elif datatype == _XSD + "decimal":
        if _DECIMAL_LEX.fullmatch(lexical):
            d = Decimal(lexical)
            if d == 0:
                return "0"
            if abs(d) < Decimal("1.7e20"):
                exponent = d.normalize().as_tuple().exponent  # an int: the lexical form is a finite number
                if isinstance(exponent, int) and -exponent <= 18:
                    return format(d.normalize(), "f")
    elif datatype == _XSD + "boolean":
        return {"1": "true", "0": "false", "true": "true", "false": "false"}.get(lexical)
    return None


@overload
def _norm_rdflib(term: Node) -> Term: ...
@overload
def _norm_rdflib(term: Node | None) -> Term | None: ...
def _norm_rdflib(term: Node | None) -> Term | None:
    """rdflib result term -> the term Oxigraph returns for the same data:
    xsd:string literals as plain literals, numbers and booleans canonical."""
    if type(term) is Literal and term.datatype is not None:
        datatype = str(term.datatype)
        if datatype == _XSD_STRING:
            return Literal(str(term))
        lexical = str(term)
        canonical = _canonical_lexical(datatype, lexical)
        if canonical is not None and canonical != lexical:
            return Literal(canonical, datatype=term.datatype)
    return term  # type: ignore[return-value]  # rdflib says Node; a Graph's terms are URIRef, Literal, BNode


@dataclass(frozen=True)
class _Prepared:
    query: SparqlQuery
    #: For ``SELECT *``: the permutation that sorts the variables by name,
    #: which is Oxigraph's order (rdflib's is a set's).
    star_order: tuple[int, ...] | None


class RdflibBackend:
    """A plain ``rdflib.Graph`` with a per-KB cache of prepared queries."""

    _CACHE_MAX = 256
    parallel_load = False  # one rdflib Graph, parsed in Python: nothing to gain, and not thread-safe

    def __init__(self) -> None:
        self.graph = rdflib.Graph(bind_namespaces="none")
        self._prepared: dict[str, _Prepared] = {}

    @property
    def triple_count(self) -> int:
        return len(self.graph)

    def load(self, path: Path, fmt: str) -> None:
        try:
            self.graph.parse(data=path.read_bytes(), format=fmt, publicID=path.resolve().as_uri())
        except Exception as exc:  # broad on purpose: rdflib's parsers raise anything
            raise KBLoadError(path, short_message(exc)) from exc

    def _prepare(self, text: str) -> _Prepared:
        prepared = self._prepared.get(text)
        if prepared is not None:
            return prepared
        from pyparsing import ParseException
        from rdflib.plugins.sparql.algebra import translateQuery
        from rdflib.plugins.sparql.parser import parseQuery

        try:
            parsed = parseQuery(text)
            query = translateQuery(parsed)
        except ParseException as exc:
            raise refuse_or_syntax(text, QuerySyntaxError(short_message(exc.msg), exc.lineno, exc.col)) from None
        except Exception as exc:  # noqa: BLE001 - broad on purpose: rdflib's translator raises plain Exceptions
            msg = short_message(exc)
            m = _UNKNOWN_PREFIX.search(msg)
            line, column = _locate(text, rf"(?<![\w<\"']){re.escape(m.group(1))}:") if m else (None, None)
            raise refuse_or_syntax(text, QuerySyntaxError(msg, line, column)) from None
        star_order = None
        if parsed[1].name == "SelectQuery" and "projection" not in parsed[1]:
            names = [str(v) for v in query.algebra["PV"]]
            star_order = tuple(sorted(range(len(names)), key=names.__getitem__))
        prepared = _Prepared(query, star_order)
        if len(self._prepared) >= self._CACHE_MAX:
            self._prepared.pop(next(iter(self._prepared)))  # oldest first
        self._prepared[text] = prepared
        return prepared

    def query(self, text: str, row_limit: int, deadline: Deadline) -> QueryResult:
        prepared = self._prepare(text)
        try:
            # SELECT bindings are a lazy generator (one row per next()); ORDER
            # BY, GROUP BY and CONSTRUCT's graph are built before the first
            # row and cannot be interrupted by the deadline.
            result = self.graph.query(prepared.query)
            if result.type == "ASK":
                return AskResult(bool(result.askAnswer))
            if result.type == "SELECT":
                variables = tuple(str(v) for v in result.vars or ())
                order = prepared.star_order
                rows_iter: Iterable[tuple[Any, ...]] = (
                    tuple(_norm_rdflib(t) for t in row)  # type: ignore[union-attr]  # SELECT rows are ResultRows
                    for row in result
                )
                if order is not None:
                    variables = tuple(variables[i] for i in order)
                    rows_iter = (tuple(row[i] for i in order) for row in rows_iter)
                rows, truncated = take(rows_iter, row_limit, deadline)
                return SelectResult(variables, tuple(rows), truncated)
            triples, truncated = take(
                ((_norm_rdflib(s), _norm_rdflib(p), _norm_rdflib(o)) for s, p, o in result.graph or ()),
                row_limit,
                deadline,
            )
            return GraphResult(tuple(triples), truncated)
        except KBError:
            raise
        except Exception as exc:  # broad on purpose: evaluation errors are the client's query's fault
            raise QueryEvaluationError(short_message(exc)) from exc


