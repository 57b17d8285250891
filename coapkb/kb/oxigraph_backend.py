"""The ``"oxigraph"`` backend: a pyoxigraph ``Store``, in memory or an
on-disk index, with results converted to rdflib terms."""

from __future__ import annotations

import re
from collections.abc import Callable, Generator, Iterable
from pathlib import Path
from typing import Any

import pyoxigraph as ox
import rdflib
from rdflib.term import BNode, Literal, URIRef

from ..model.results import AskResult, GraphResult, QueryResult, SelectResult, Term, Triple
from .errors import KBError, KBLoadError, QueryEvaluationError, QuerySyntaxError, short_message
from .limits import Deadline, take
from .refusals import refuse_or_syntax

_XSD_STRING = "http://www.w3.org/2001/XMLSchema#string"
_RDF_LANGSTRING = "http://www.w3.org/1999/02/22-rdf-syntax-ns#langString"

#: rdflib format name -> pyoxigraph's native parser; others go through rdflib.
_OX_FORMATS = {
    "xml": ox.RdfFormat.RDF_XML,
    "turtle": ox.RdfFormat.TURTLE,
    "nt": ox.RdfFormat.N_TRIPLES,
}


_OX_POSITION = re.compile(r"^error at (\d+):(\d+):\s*(.*)$", re.DOTALL)


def _offset(text: str, line: int, column: int) -> int:
    """Character offset of a 1-based line/column."""
    start = 0
    for _ in range(line - 1):
        nl = text.find("\n", start)
        if nl < 0:
            return len(text)
        start = nl + 1
    return min(start + column - 1, len(text))


_PNAME_BEFORE = re.compile(r"(?<![\w<\"'?$])([A-Za-z][\w.-]*)?:[\w.-]*$")


def _ox_syntax_message(message: str, text: str, line: int, column: int) -> str:
    """Oxigraph's PEG message made readable.

    It lists every alternative tried at the furthest position reached,
    Unicode character classes included (``['A' ..= 'Z' | ...]``); keep the
    keywords and punctuation, and name an undeclared prefix when that is
    what went wrong.  The position is the furthest one the parser reached,
    often the end of the query rather than the offending token.
    """
    _, sep, alternatives = " ".join(message.split()).partition("expected ")
    alternatives = alternatives.removeprefix("one of ")
    words = [a for a in re.split(r",\s*(?=[A-Z\"'\[])", alternatives) if a and not a.startswith("[")] if sep else []
    offset = _offset(text, line, column)
    if "Prefix not found" in words:
        m = _PNAME_BEFORE.search(text[max(0, offset - 200) : offset])  # bounded: no quadratic search
        if m:
            return f"undeclared prefix '{(m.group(1) or '')[:40]}:' (add a PREFIX declaration)"
    if words:
        return short_message("expected " + (words[0] if len(words) == 1 else "one of " + ", ".join(words)))
    rest = text[offset:].split()
    return f"syntax error near {rest[0][:20]!r}" if rest else "syntax error (reached the end of the query)"


QUERY_FORMS = ("SELECT", "CONSTRUCT", "ASK", "DESCRIBE")
UPDATE_FORMS = ("INSERT", "DELETE", "LOAD", "CLEAR", "CREATE", "DROP", "ADD", "MOVE", "COPY", "WITH")
_PROLOGUE = re.compile(r"(?:\s+|#[^\n]*|(?:PREFIX|BASE)\b[^<]*<[^>]*>)*", re.IGNORECASE)
_WORD = re.compile(r"[A-Za-z]+")


def _unknown_form(text: str, forms: tuple[str, ...]) -> QuerySyntaxError | None:
    """A misspelt first keyword (``SELEC``), said as such: Oxigraph reports
    what it expected at the furthest point it reached, often far from it."""
    start = _PROLOGUE.match(text)
    at = start.end() if start else 0
    word = _WORD.match(text, at)
    if word is None or word.group().upper() in forms:
        return None
    line = text.count("\n", 0, at) + 1
    column = at - (text.rfind("\n", 0, at) + 1) + 1
    return QuerySyntaxError(f"expected {', '.join(forms[:-1])} or {forms[-1]}, not {word.group()[:20]!r}", line, column)


def syntax_error(message: str, text: str, forms: tuple[str, ...] = QUERY_FORMS) -> QuerySyntaxError:
    """Oxigraph's syntax error on ``text`` (a query, or an update with
    ``forms=UPDATE_FORMS``), readable, with its position."""
    unknown = _unknown_form(text, forms)
    if unknown is not None:
        return unknown
    m = _OX_POSITION.match(message)
    if m is None:
        return QuerySyntaxError(short_message(message))
    line, column = int(m.group(1)), int(m.group(2))
    return QuerySyntaxError(_ox_syntax_message(m.group(3), text, line, column), line, column)


class OxigraphBackend:
    """pyoxigraph ``Store`` in memory; results converted to rdflib terms."""

    #: Converted terms are cached (they are immutable); bounded so a KB that
    #: answers many different queries does not grow without end.
    _CACHE_MAX = 50_000

    #: pyoxigraph would parse the files side by side (GIL released), but
    #: concurrent loads interleave in the store and the order of unordered
    #: results then differs from load to load: a KB's answers must not.
    parallel_load = False

    def __init__(self, store: ox.Store | None = None, triple_count: int | None = None) -> None:
        self.store = ox.Store() if store is None else store
        #: On disk, building goes through bulk_load (no transaction log):
        #: many times faster there, and the index is not in use until built.
        self._bulk = store is not None
        #: An on-disk index (it is never written after it is built).
        self.on_disk = triple_count is not None
        self._triple_count = triple_count
        self._terms: dict[object, Term] = {}

    @property
    def triple_count(self) -> int:
        # Counting an on-disk store scans it (0.4 s for 1.9 M triples): an
        # index remembers its count.
        return len(self.store) if self._triple_count is None else self._triple_count

    def load(self, path: Path, fmt: str) -> None:
        base = path.resolve().as_uri()
        native = _OX_FORMATS.get(fmt)
        try:
            if native is not None:
                # Store.load from the path: Oxigraph reads the file itself (no
                # copy of it in Python) and parses and inserts in one pass.
                # bulk_load is no faster for an in-memory store and peaks
                # ~150 MB higher on the 100k-product KB; lenient=True would
                # save ~10 % but lets invalid IRIs and language tags in
                # (experiments/kb_load.py).
                load = self.store.bulk_load if self._bulk else self.store.load
                load(path=path, format=native, base_iri=base)
                return
            graph = rdflib.Graph(bind_namespaces="none")
            graph.parse(data=path.read_bytes(), format=fmt, publicID=base)
        except Exception as exc:  # broad on purpose: parsers raise SyntaxError, ValueError, OSError, ...
            raise KBLoadError(path, short_message(exc)) from exc
        extend = self.store.bulk_extend if self._bulk else self.store.extend
        extend(
            ox.Quad(_to_ox(s), _to_ox(p), _to_ox(o))  # type: ignore[arg-type]  # rdflib checked the positions
            for s, p, o in graph
        )

    def _convert(self, term: object) -> Term:
        cached = self._terms.get(term)
        if cached is not None:
            return cached
        converted = _from_ox(term)
        if len(self._terms) >= self._CACHE_MAX:
            self._terms.clear()
        self._terms[term] = converted
        return converted

    def query(self, text: str, row_limit: int, deadline: Deadline) -> QueryResult:
        try:
            # Parses and plans; evaluation is lazy, one solution per next().
            result = self.store.query(text)
        except SyntaxError as exc:
            raise refuse_or_syntax(text, syntax_error(str(exc), text)) from None
        except Exception as exc:  # broad on purpose: OSError from the store, anything else from planning
            raise QueryEvaluationError(short_message(exc)) from exc
        # What the deadline cannot interrupt: Oxigraph evaluates inside Rust
        # between two solutions, so a single next() that must first sort
        # (ORDER BY), group/aggregate (GROUP BY, COUNT), or scan a large join
        # whose FILTER rejects everything runs to completion before the next
        # check.  The server's outer asyncio timeout answers the client then,
        # but the worker thread keeps computing until that next() returns.
        convert = self._convert
        # Oxigraph's results may be dropped only on the thread that made them
        # (a query runs on a worker thread): each generator over them is
        # closed and the last reference dropped here, not left to a cycle
        # through an exception's traceback that the collector frees on
        # another thread ("PyQuerySolutions is unsendable").
        readers: list[Generator[Any, None, None]] = []
        try:
            if isinstance(result, ox.QueryBoolean):
                return AskResult(bool(result))
            if isinstance(result, ox.QuerySolutions):
                variables = tuple(v.value for v in result.variables)
                readers.append(tuple(None if t is None else convert(t) for t in solution) for solution in result)
                rows, truncated = take(readers[0], row_limit, deadline)
                return SelectResult(variables, tuple(rows), truncated)
            # CONSTRUCT/DESCRIBE: a graph is a set, Oxigraph may repeat triples.
            readers.append(_triples_from_ox(result, convert))
            readers.append(_unique(readers[0]))
            triples, truncated = take(readers[1], row_limit, deadline)
            return GraphResult(tuple(triples), truncated)
        except KBError:
            raise
        except Exception as exc:  # broad on purpose: evaluation errors are the query's, not the server's
            raise QueryEvaluationError(short_message(exc)) from exc
        finally:
            for reader in reversed(readers):
                reader.close()
            del result


def _unique(triples: Iterable[Triple]) -> Generator[Triple, None, None]:
    seen: set[Triple] = set()
    for t in triples:
        if t not in seen:
            seen.add(t)
            yield t


def _triples_from_ox(result: Iterable[ox.Triple], convert: Callable[[object], Term]) -> Generator[Triple, None, None]:
    for triple in result:
        yield convert(triple.subject), convert(triple.predicate), convert(triple.object)


def _from_ox(term: object) -> Term:
    """pyoxigraph term -> rdflib term, keeping datatype and language.

    xsd:string literals become rdflib plain literals: the same RDF 1.1 term,
    and the form rdflib's parsers produce, so both backends compare equal.
    """
    if type(term) is ox.NamedNode:
        return URIRef(term.value)
    if type(term) is ox.Literal:
        datatype = term.datatype.value
        if datatype == _XSD_STRING:
            return Literal(term.value)
        if datatype == _RDF_LANGSTRING:
            return Literal(term.value, lang=term.language)
        return Literal(term.value, datatype=URIRef(datatype))
    if type(term) is ox.BlankNode:
        return BNode(term.value)
    raise QueryEvaluationError(f"cannot represent {type(term).__name__} terms (RDF-star) in results")


def _to_ox(term: object) -> ox.NamedNode | ox.BlankNode | ox.Literal:
    # The usual kinds first, by their exact type: isinstance is slower, and
    # a write or a join converts every triple it changes.
    if type(term) is URIRef:
        return ox.NamedNode(term)
    if type(term) is Literal and term.language is None and term.datatype is None:
        return ox.Literal(term)
    if isinstance(term, URIRef):
        return ox.NamedNode(str(term))
    if isinstance(term, BNode):
        return ox.BlankNode(str(term))
    if isinstance(term, Literal):
        if term.language:
            return ox.Literal(str(term), language=term.language)
        if term.datatype is not None:
            return ox.Literal(str(term), datatype=ox.NamedNode(str(term.datatype)))
        return ox.Literal(str(term))
    raise TypeError(f"unsupported rdflib term {term!r}")


