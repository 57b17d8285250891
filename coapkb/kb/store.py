"""A robot's read-only knowledge base: RDF files answering SPARQL queries.

Two interchangeable backends give identical :mod:`coapkb.kb.results`:

* ``"oxigraph"`` (default): a pyoxigraph in-memory ``Store``.  About
  0.03 ms per lookup query, flat in the KB size, and ~20x faster loading
  than rdflib (docs: perf-anchors section 1).
* ``"rdflib"``: a plain ``rdflib.Graph``, the seed paper's library.  Parsing
  a query string costs ~3 ms, so prepared queries are cached by query text.

A KB is read-only: SPARQL Update is refused, and every query runs under a
row limit and an optional time budget, so one request cannot starve a robot.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
import threading
import time
import xml.etree.ElementTree as ET
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from decimal import Decimal
from pathlib import Path
from typing import Protocol
from collections.abc import Callable, Iterable, Iterator, Sequence

import pyoxigraph as ox
import rdflib
from rdflib.plugins.sparql.sparql import Query as SparqlQuery
from rdflib.term import BNode, Literal, URIRef

from ..errors import CoapkbError
from .results import AskResult, GraphResult, QueryResult, SelectResult, Term, Triple

__all__ = [
    "BACKENDS",
    "FeatureRefused",
    "KBError",
    "KBLoadError",
    "KnowledgeBase",
    "QueryEvaluationError",
    "QueryRefused",
    "QuerySyntaxError",
    "QueryTimeout",
    "UpdateRefused",
]

BACKENDS = ("oxigraph", "rdflib")

_XSD_STRING = "http://www.w3.org/2001/XMLSchema#string"
_RDF_LANGSTRING = "http://www.w3.org/1999/02/22-rdf-syntax-ns#langString"


# --------------------------------------------------------------------------
# Errors


class KBError(CoapkbError):
    """Base of every knowledge-base error; the message is fit for a client."""


class KBLoadError(KBError):
    """A file could not be read or parsed."""

    def __init__(self, path: str | Path, message: str) -> None:
        self.path = str(path)
        self.message = message
        super().__init__(f"{self.path}: {message}")


class QuerySyntaxError(KBError):
    """The query is not valid SPARQL 1.1 (line/column 1-based, None if unknown)."""

    def __init__(self, message: str, line: int | None = None, column: int | None = None) -> None:
        self.message = message
        self.line = line
        self.column = column
        where = f"line {line}, column {column}: " if line is not None and column is not None else ""
        super().__init__(where + message)


class QueryRefused(KBError):
    """The request is SPARQL, but asks for something a robot does not do."""


class UpdateRefused(QueryRefused):
    """The request is SPARQL Update; a robot's KB is read-only."""

    def __init__(self, operations: Sequence[str]) -> None:
        self.operations = tuple(operations)
        ops = ", ".join(self.operations) or "update"
        super().__init__(f"SPARQL Update ({ops}) is not accepted: the knowledge base is read-only")


class FeatureRefused(QueryRefused):
    """The query uses ``SERVICE`` or ``FROM``/``FROM NAMED``.

    Both backends would fetch those IRIs over HTTP (rdflib and Oxigraph
    implement federation and, for rdflib, remote ``FROM`` graphs): a query
    from the network must not make a robot open connections elsewhere, and
    a blocking fetch cannot be interrupted by the time budget.
    """

    def __init__(self, feature: str) -> None:
        self.feature = feature
        why = (
            "federated queries are not accepted: a robot answers from its own knowledge base only"
            if feature == "SERVICE"
            else "dataset clauses are not accepted: the knowledge base is a single default graph"
        )
        super().__init__(f"{feature}: {why}")


class QueryTimeout(KBError):
    """The query ran past its time budget."""

    def __init__(self, budget_s: float, rows: int) -> None:
        self.budget_s = budget_s
        self.rows = rows
        super().__init__(f"query exceeded its {budget_s:g} s time budget after {rows} results")


class QueryEvaluationError(KBError):
    """The query parsed but failed while being evaluated."""


# --------------------------------------------------------------------------
# File formats and prefixes

#: suffix -> rdflib format name.
_SUFFIX_FORMATS = {
    ".owl": "xml",
    ".rdf": "xml",
    ".xml": "xml",
    ".ttl": "turtle",
    ".turtle": "turtle",
    ".nt": "nt",
    ".ntriples": "nt",
    ".n3": "n3",
    ".jsonld": "json-ld",
    ".json-ld": "json-ld",
}

#: rdflib format name -> pyoxigraph's native parser; others go through rdflib.
_OX_FORMATS = {
    "xml": ox.RdfFormat.RDF_XML,
    "turtle": ox.RdfFormat.TURTLE,
    "nt": ox.RdfFormat.N_TRIPLES,
}

_TURTLE_PREFIX = re.compile(
    rb"^[ \t]*(?:@prefix|PREFIX)[ \t]+([A-Za-z][A-Za-z0-9_.-]*)?:[ \t]*<([^>\s]*)>", re.MULTILINE | re.IGNORECASE
)


def _format_for(path: Path, head: bytes) -> str:
    """The file's format from its suffix (and, for ``.owl``, its first bytes)."""
    suffix = path.suffix.lower()
    fmt = _SUFFIX_FORMATS.get(suffix)
    if fmt is None:
        fmt = rdflib.util.guess_format(path.name)
    if fmt is None:
        raise KBLoadError(path, f"unknown RDF format for suffix {suffix!r} (use .owl/.rdf, .ttl, .nt, .n3, .jsonld)")
    if suffix == ".owl" and not head.lstrip(b"\xef\xbb\xbf \t\r\n").startswith(b"<"):
        fmt = "turtle"  # Protege can save .owl files as Turtle too
    return fmt


_TAIL = 1 << 16


def _xml_root(path: Path, size: int) -> dict[str, str]:
    """The prefixes an RDF/XML file declares on its root, after checking that
    the file ends with the root's end tag.

    Prefixes: the root element's ``xmlns:p`` attributes, read by an
    incremental parser that stops at the root (large files cost nothing).
    End tag: Oxigraph's RDF/XML parser accepts a document that stops after
    any complete element, so a file cut short at an element boundary (a
    partial copy) would load part of a KB without a word; the last bytes
    tell.  Malformed heads are left to the real parser and its message.
    """
    found: dict[str, str] = {}
    default_ns: str | None = None
    root: str | None = None
    try:
        with path.open("rb") as f:
            for event, item in ET.iterparse(f, events=("start-ns", "start")):
                if event == "start":
                    root = item.tag  # type: ignore[union-attr]
                    break
                prefix, uri = item  # type: ignore[misc]
                if prefix:
                    found.setdefault(prefix, uri)
                else:
                    default_ns = uri
            if root is None:
                return found  # no element at all: the parser will say so
            f.seek(max(0, size - _TAIL))
            tail = f.read()
    except ET.ParseError:
        return found  # the real parser reports the error with its own message
    except OSError as exc:
        raise KBLoadError(path, exc.strerror or str(exc)) from exc
    uri, _, local = root.rpartition("}")
    uri = uri.lstrip("{")
    names = {f"{p}:{local}" for p, u in found.items() if u == uri}
    if uri == (default_ns or ""):
        names.add(local)
    # What may follow the root: whitespace, comments, processing instructions.
    body = tail.rstrip()
    while body.endswith((b"-->", b"?>")):
        start = body.rfind(b"<!--" if body.endswith(b"-->") else b"<?")
        if start < 0:
            break
        body = body[:start].rstrip()
    start = body.rfind(b"</")
    last = body[start + 2 : -1].strip().decode("utf-8", "replace") if start >= 0 and body.endswith(b">") else None
    if last not in names:
        if not (body.endswith(b"/>") and b"</" not in tail and size <= _TAIL):  # an empty <rdf:RDF/>
            expected = min(names) if names else local
            raise KBLoadError(path, f"truncated: the file does not end with the root element's end tag </{expected}>")
    return found


def _turtle_prefixes(data: bytes, found: dict[str, str]) -> None:
    """``@prefix``/``PREFIX`` lines of Turtle or N3 (whole lines) into ``found``."""
    if b"prefix" not in data.lower():
        return  # 5x faster than the regex on data without any: most chunks of a big file
    for m in _TURTLE_PREFIX.finditer(data):
        if m.group(1):
            found.setdefault(m.group(1).decode(), m.group(2).decode())


_CHUNK = 1 << 20


@dataclass
class _KBFile:
    """A KB file as first seen: its format, what says it has not changed, and
    the prefixes it declares (the first declaration of a prefix wins; the
    default namespace is left out: every module has its own, so it names
    nothing across a multi-file KB)."""

    path: Path
    fmt: str
    size: int
    stamp: tuple[int, int, int, int]  # st_dev, st_ino, st_size, st_mtime_ns
    prefixes: dict[str, str]

    @classmethod
    def open(cls, path: Path) -> _KBFile:
        try:
            with path.open("rb") as f:
                st = os.fstat(f.fileno())
                head = f.read(_TAIL)
        except OSError as exc:
            raise KBLoadError(path, exc.strerror or str(exc)) from exc
        fmt = _format_for(path, head)
        prefixes = _xml_root(path, st.st_size) if fmt == "xml" else {}
        return cls(path, fmt, st.st_size, _stamp(st), prefixes)

    def hash_into(self, digest: hashlib._Hash) -> None:  # type: ignore[name-defined]
        """Feed the file's name, size and bytes to ``digest``; collect Turtle
        prefixes on the way.  Reads in chunks (hashlib releases the GIL), so
        it runs beside a parse on another thread without holding the file."""
        digest.update(self.path.name.encode() + b"\0" + self.size.to_bytes(8, "big"))
        turtle = self.fmt in ("turtle", "n3")
        carry = b""
        read = 0
        try:
            with self.path.open("rb") as f:
                while chunk := f.read(_CHUNK):
                    read += len(chunk)
                    digest.update(chunk)
                    if turtle:
                        text = carry + chunk
                        cut = text.rfind(b"\n") + 1
                        _turtle_prefixes(text[:cut], self.prefixes)
                        carry = text[cut:]
        except OSError as exc:
            raise KBLoadError(self.path, exc.strerror or str(exc)) from exc
        if turtle and carry:
            _turtle_prefixes(carry, self.prefixes)
        if read != self.size:
            raise KBLoadError(self.path, "the file changed while it was being loaded")

    def check_unchanged(self) -> None:
        """The bytes hashed are the bytes parsed: the file was not modified or
        replaced while it was read twice (hash, parse)."""
        try:
            unchanged = _stamp(self.path.stat()) == self.stamp
        except OSError:
            unchanged = False
        if not unchanged:
            raise KBLoadError(self.path, "the file changed while it was being loaded")


def _stamp(st: os.stat_result) -> tuple[int, int, int, int]:
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns


def _message(exc: BaseException | str) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= 300 else text[:297] + "..."


# --------------------------------------------------------------------------
# Query-error helpers shared by both backends

# Each alternative of the prologue can match a given text in one way only,
# so a failing match cannot backtrack exponentially (queries come from the
# network).
_UPDATE_KEYWORD = re.compile(
    r"(?:\s|\#[^\n]*(?:\n|$)|(?:PREFIX|BASE)\b[^<]*<[^>]*>)*"
    r"(INSERT|DELETE|LOAD|CLEAR|CREATE|DROP|COPY|MOVE|ADD|WITH)\b",
    re.IGNORECASE,
)

_ANY_UPDATE_WORD = re.compile(r"\b(?:INSERT|DELETE|LOAD|CLEAR|CREATE|DROP|COPY|MOVE|ADD)\b", re.IGNORECASE)

_UPDATE_OPERATION_NAMES = {
    "InsertData": "INSERT DATA",
    "DeleteData": "DELETE DATA",
    "DeleteWhere": "DELETE WHERE",
    "Modify": "DELETE/INSERT",
    "Load": "LOAD",
    "Clear": "CLEAR",
    "Drop": "DROP",
    "Create": "CREATE",
    "Add": "ADD",
    "Move": "MOVE",
    "Copy": "COPY",
}


def _update_operations(text: str) -> tuple[str, ...] | None:
    """The operations of ``text`` if it is SPARQL Update, else None.

    Only called once a text has failed to parse as a query.  rdflib's update
    grammar only parses (nothing is executed); a text that starts like an
    update but does not parse as one still counts, so a malformed update
    gets "refused" rather than a confusing "expected SELECT" error.
    """
    from rdflib.plugins.sparql.parser import parseUpdate

    if _ANY_UPDATE_WORD.search(text) is None:
        return None  # spare pyparsing (~0.1 s on a long malformed query)
    try:
        parsed = parseUpdate(text)
    except Exception:  # broad on purpose: any failure means "not a valid update"
        parsed = None
    if parsed is not None and "request" in parsed:  # an empty update (prologue only) is no update
        ops = tuple(_UPDATE_OPERATION_NAMES.get(r.name, r.name.upper()) for r in parsed["request"])
        if ops:
            return ops
    m = _UPDATE_KEYWORD.match(text)
    return (m.group(1).upper(),) if m else None


_OX_POSITION = re.compile(r"^error at (\d+):(\d+):\s*(.*)$", re.DOTALL)
_UNKNOWN_PREFIX = re.compile(r"Unknown namespace prefix\s*:\s*(\S+)")


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
        return _message("expected " + (words[0] if len(words) == 1 else "one of " + ", ".join(words)))
    rest = text[offset:].split()
    return f"syntax error near {rest[0][:20]!r}" if rest else "syntax error (reached the end of the query)"


def _locate(text: str, needle_regex: str) -> tuple[int | None, int | None]:
    m = re.search(needle_regex, text)
    if m is None:
        return None, None
    line = text.count("\n", 0, m.start()) + 1
    column = m.start() - (text.rfind("\n", 0, m.start()) + 1) + 1
    return line, column


def _refuse_or_syntax(text: str, error: QuerySyntaxError) -> KBError:
    ops = _update_operations(text)
    return UpdateRefused(ops) if ops else error


_TOKENS = re.compile(
    r'"""(?:[^"\\]|\\.|"(?!""))*"""'  # long strings
    r"|'''(?:[^'\\]|\\.|'(?!''))*'''"
    r'|"(?:[^"\\\n]|\\.)*"'  # short strings
    r"|'(?:[^'\\\n]|\\.)*'"
    r'|<[^<>"{}|^`\\\s]*>'  # IRIs
    r"|\#[^\n]*"  # comments
    r"|[?$]\w+"  # variables
    r"|(?<![\w:.-])(SERVICE|FROM)(?![\w:-])",  # the keywords, not in prefixed names
    re.IGNORECASE,
)


def _refused_feature(text: str) -> str | None:
    """``SERVICE`` or ``FROM`` if the query uses it as a keyword (outside
    strings, IRIs, comments and names), else None.  A substring test first
    keeps the common case at ~1 us."""
    lowered = text.lower()
    if "service" not in lowered and "from" not in lowered:
        return None
    for m in _TOKENS.finditer(text):
        if m.group(1):
            return m.group(1).upper()
    return None


class _Deadline:
    """Checks a monotonic deadline between results."""

    __slots__ = ("budget", "end")

    def __init__(self, budget_s: float | None) -> None:
        self.budget = budget_s
        self.end = None if budget_s is None else time.monotonic() + budget_s

    def check(self, rows: int) -> None:
        if self.end is not None and time.monotonic() > self.end:
            raise QueryTimeout(self.budget or 0.0, rows)


def _take(items: Iterable[Term | tuple], limit: int, deadline: _Deadline) -> tuple[list, bool]:
    """Up to ``limit`` items, and whether more existed; checks the deadline
    after every item (one ``next()`` on a lazy result = evaluating up to the
    next solution)."""
    out: list = []
    for item in items:
        if len(out) == limit:
            return out, True
        out.append(item)
        deadline.check(len(out))
    return out, False


# --------------------------------------------------------------------------
# Backends


class _Backend(Protocol):
    #: whether :meth:`load` may run for several files at once, on threads
    parallel_load: bool

    @property
    def triple_count(self) -> int: ...

    def load(self, path: Path, fmt: str) -> None: ...

    def query(self, text: str, row_limit: int, deadline: _Deadline) -> QueryResult: ...


class _OxigraphBackend:
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
            raise KBLoadError(path, _message(exc)) from exc
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

    def query(self, text: str, row_limit: int, deadline: _Deadline) -> QueryResult:
        try:
            # Parses and plans; evaluation is lazy, one solution per next().
            result = self.store.query(text)
        except SyntaxError as exc:
            msg = str(exc)
            m = _OX_POSITION.match(msg)
            if m:
                line, column = int(m.group(1)), int(m.group(2))
                error = QuerySyntaxError(_ox_syntax_message(m.group(3), text, line, column), line, column)
            else:
                error = QuerySyntaxError(_message(msg))
            raise _refuse_or_syntax(text, error) from None
        except Exception as exc:  # broad on purpose: OSError from the store, anything else from planning
            raise QueryEvaluationError(_message(exc)) from exc
        # What the deadline cannot interrupt: Oxigraph evaluates inside Rust
        # between two solutions, so a single next() that must first sort
        # (ORDER BY), group/aggregate (GROUP BY, COUNT), or scan a large join
        # whose FILTER rejects everything runs to completion before the next
        # check.  The server's outer asyncio timeout answers the client then,
        # but the worker thread keeps computing until that next() returns.
        convert = self._convert
        try:
            if isinstance(result, ox.QueryBoolean):
                return AskResult(bool(result))
            if isinstance(result, ox.QuerySolutions):
                variables = tuple(v.value for v in result.variables)
                rows, truncated = _take(
                    (tuple(None if t is None else convert(t) for t in solution) for solution in result),
                    row_limit,
                    deadline,
                )
                return SelectResult(variables, tuple(rows), truncated)
            # CONSTRUCT/DESCRIBE: a graph is a set, Oxigraph may repeat triples.
            triples, truncated = _take(_unique(_triples_from_ox(result, convert)), row_limit, deadline)
            return GraphResult(tuple(triples), truncated)
        except KBError:
            raise
        except Exception as exc:  # broad on purpose: evaluation errors are the query's, not the server's
            raise QueryEvaluationError(_message(exc)) from exc


#: Written last into a built index: an index without it is not complete.
_INDEX_MANIFEST = "coapkb-index.json"


def _open_or_build_index(path: Path, files: list[_KBFile]) -> _OxigraphBackend:
    """Open the on-disk index at ``path`` read-only, building it first if
    it does not exist (robots of one host may share an index directory)."""
    manifest = path / _INDEX_MANIFEST
    if not manifest.exists():
        _build_index(path, files)
    try:
        triples = int(json.loads(manifest.read_text())["triples"])
        store = ox.Store.read_only(str(path))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise KBLoadError(path, f"unreadable KB index ({_message(exc)}); delete it to have it rebuilt") from exc
    return _OxigraphBackend(store, triples)


def _build_index(path: Path, files: list[_KBFile]) -> None:
    """Build the index in a private directory beside ``path`` and move it
    into place only when complete, so a crash or a concurrent builder never
    leaves a half-built index under the final name."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        building = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    except OSError as exc:
        raise KBLoadError(path.parent, f"cannot create the KB index: {exc.strerror or exc}") from exc
    try:
        engine = _OxigraphBackend(ox.Store(str(building)))
        for f in files:
            engine.load(f.path, f.fmt)
        for f in files:  # the index must hold the bytes its name hashes
            f.check_unchanged()
        engine.store.optimize()
        triples = len(engine.store)
        engine.store.flush()
        del engine  # closes the store before its directory moves
        manifest = {"triples": triples, "oxigraph": ox.__version__, "files": [str(f.path) for f in files]}
        (building / _INDEX_MANIFEST).write_text(json.dumps(manifest))
        try:
            building.rename(path)
        except OSError:
            if not (path / _INDEX_MANIFEST).exists():
                raise
            # Another robot built the same index meanwhile: keep theirs.
    except OSError as exc:
        raise KBLoadError(path, f"cannot build the KB index: {exc.strerror or exc}") from exc
    finally:
        shutil.rmtree(building, ignore_errors=True)


def _unique(triples: Iterable[Triple]) -> Iterator[Triple]:
    seen: set[Triple] = set()
    for t in triples:
        if t not in seen:
            seen.add(t)
            yield t


def _triples_from_ox(result: Iterable[object], convert: Callable[[object], Term]) -> Iterator[Triple]:
    for triple in result:
        yield convert(triple.subject), convert(triple.predicate), convert(triple.object)  # type: ignore[attr-defined]


def _from_ox(term: object) -> Term:
    """pyoxigraph term -> rdflib term, keeping datatype and language.

    xsd:string literals become rdflib plain literals: the same RDF 1.1 term,
    and the form rdflib's parsers produce, so both backends compare equal.
    """
    cls = type(term)
    if cls is ox.NamedNode:
        return URIRef(term.value)  # type: ignore[attr-defined]
    if cls is ox.Literal:
        datatype = term.datatype.value  # type: ignore[attr-defined]
        if datatype == _XSD_STRING:
            return Literal(term.value)  # type: ignore[attr-defined]
        if datatype == _RDF_LANGSTRING:
            return Literal(term.value, lang=term.language)  # type: ignore[attr-defined]
        return Literal(term.value, datatype=URIRef(datatype))  # type: ignore[attr-defined]
    if cls is ox.BlankNode:
        return BNode(term.value)  # type: ignore[attr-defined]
    raise QueryEvaluationError(f"cannot represent {cls.__name__} terms (RDF-star) in results")


def _to_ox(term: object) -> ox.NamedNode | ox.BlankNode | ox.Literal:
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
            if abs(d) < Decimal("1.7e20") and -d.normalize().as_tuple().exponent <= 18:  # type: ignore[operator]
                return format(d.normalize(), "f")
    elif datatype == _XSD + "boolean":
        return {"1": "true", "0": "false", "true": "true", "false": "false"}.get(lexical)
    return None


def _norm_rdflib(term: object) -> Term | None:
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
    return term  # type: ignore[return-value]


@dataclass(frozen=True)
class _Prepared:
    query: SparqlQuery
    #: For ``SELECT *``: the permutation that sorts the variables by name,
    #: which is Oxigraph's order (rdflib's is a set's).
    star_order: tuple[int, ...] | None


class _RdflibBackend:
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
            raise KBLoadError(path, _message(exc)) from exc

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
            raise _refuse_or_syntax(text, QuerySyntaxError(_message(exc.msg), exc.lineno, exc.col)) from None
        except Exception as exc:  # broad on purpose: rdflib's translator raises plain Exceptions
            msg = _message(exc)
            m = _UNKNOWN_PREFIX.search(msg)
            line, column = _locate(text, rf"(?<![\w<\"']){re.escape(m.group(1))}:") if m else (None, None)
            raise _refuse_or_syntax(text, QuerySyntaxError(msg, line, column)) from None
        star_order = None
        if parsed[1].name == "SelectQuery" and "projection" not in parsed[1]:
            names = [str(v) for v in query.algebra["PV"]]
            star_order = tuple(sorted(range(len(names)), key=names.__getitem__))
        prepared = _Prepared(query, star_order)
        if len(self._prepared) >= self._CACHE_MAX:
            self._prepared.pop(next(iter(self._prepared)))  # oldest first
        self._prepared[text] = prepared
        return prepared

    def query(self, text: str, row_limit: int, deadline: _Deadline) -> QueryResult:
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
                rows_iter: Iterable[tuple] = (
                    tuple(_norm_rdflib(t) for t in row)  # type: ignore[union-attr]  # SELECT rows are ResultRows
                    for row in result
                )
                if order is not None:
                    variables = tuple(variables[i] for i in order)
                    rows_iter = (tuple(row[i] for i in order) for row in rows_iter)
                rows, truncated = _take(rows_iter, row_limit, deadline)
                return SelectResult(variables, tuple(rows), truncated)
            triples, truncated = _take(
                ((_norm_rdflib(s), _norm_rdflib(p), _norm_rdflib(o)) for s, p, o in result.graph or ()),
                row_limit,
                deadline,
            )
            return GraphResult(tuple(triples), truncated)  # type: ignore[arg-type]
        except KBError:
            raise
        except Exception as exc:  # broad on purpose: evaluation errors are the client's query's fault
            raise QueryEvaluationError(_message(exc)) from exc


# --------------------------------------------------------------------------
# The knowledge base


class KnowledgeBase:
    """One robot's KB: the union of some RDF files, queried with SPARQL 1.1.

    Use :meth:`load`.  Attributes: ``names`` (the files' stems, e.g.
    ``("Object",)``, which decide the named queries a robot offers),
    ``prefixes`` (prefix -> namespace declared in the files; the first file
    declaring a prefix wins), ``triple_count``, ``etag`` (8 bytes, changes
    whenever file content or backend changes: clients and caches use it to
    tell answers from different KB versions apart) and ``backend``.
    """

    def __init__(
        self,
        backend: str,
        engine: _Backend,
        names: tuple[str, ...],
        paths: tuple[Path, ...],
        prefixes: dict[str, str],
        etag: bytes,
    ) -> None:
        self.backend = backend
        self._engine = engine
        self.names = names
        self.paths = paths
        self.prefixes = prefixes
        self.etag = etag
        self.triple_count = engine.triple_count

    def __repr__(self) -> str:
        return f"<KnowledgeBase {'+'.join(self.names)} {self.triple_count} triples ({self.backend})>"

    @classmethod
    def load(
        cls, paths: Sequence[str | Path], backend: str = "oxigraph", *, index_dir: str | Path | None = None
    ) -> KnowledgeBase:
        """Load RDF files (format from the suffix) into a new KB.

        With ``index_dir`` (oxigraph only) the KB is an on-disk index in that
        directory, named by the files' content: built once (slower than a
        load into memory), then opened in milliseconds by every later start
        from the same files; queries run 1-3x slower than in memory.
        Raises :class:`KBLoadError` naming the file for an unreadable or
        malformed file, ``ValueError`` for an unknown backend or no files.
        """
        if backend not in BACKENDS:
            raise ValueError(f"unknown backend {backend!r}; use one of {', '.join(BACKENDS)}")
        if isinstance(paths, (str, Path)):
            paths = [paths]
        if not paths:
            raise ValueError("a knowledge base needs at least one file")
        if index_dir is not None and backend != "oxigraph":
            raise ValueError(f"an on-disk index needs the oxigraph backend, not {backend!r}")
        # Unreadable, unknown or truncated files are reported before any parsing.
        files = [_KBFile.open(Path(item)) for item in paths]
        if index_dir is not None:
            return cls._open_index(files, Path(index_dir))
        engine: _Backend = _OxigraphBackend() if backend == "oxigraph" else _RdflibBackend()
        # Parsing is nearly all of a big KB's load time: the files are parsed
        # one after another on a worker thread (GIL released) while this
        # thread hashes them for the ETag.
        digest = hashlib.blake2b(digest_size=8)
        digest.update(backend.encode() + b"\0")
        stop = threading.Event()

        def load_in_order(batch: list[_KBFile]) -> None:
            for f in batch:  # after a failure, the next files are not parsed
                if stop.is_set():
                    return
                engine.load(f.path, f.fmt)

        batches = [[f] for f in files] if engine.parallel_load else [files]
        with ThreadPoolExecutor(max_workers=len(batches)) as pool:
            loads = [pool.submit(load_in_order, batch) for batch in batches]
            try:
                for f in files:
                    f.hash_into(digest)
                for load in loads:  # the first failing file, in the order given
                    load.result()
            except BaseException:
                stop.set()
                raise
        for f in files:
            f.check_unchanged()
        return cls._assemble(backend, engine, files, digest.digest())

    @classmethod
    def _open_index(cls, files: list[_KBFile], index_dir: Path) -> KnowledgeBase:
        # An index returns unordered results in its own key order, not in
        # the in-memory store's insertion order: its answers get other ETags.
        digest = hashlib.blake2b(digest_size=8)
        digest.update(f"oxigraph-index {ox.__version__}\0".encode())
        for f in files:
            f.hash_into(digest)
        etag = digest.digest()
        engine = _open_or_build_index(index_dir / f"{etag.hex()}.oxigraph", files)
        return cls._assemble("oxigraph", engine, files, etag)

    @classmethod
    def _assemble(cls, backend: str, engine: _Backend, files: list[_KBFile], etag: bytes) -> KnowledgeBase:
        prefixes: dict[str, str] = {}
        for f in files:
            for prefix, ns in f.prefixes.items():
                prefixes.setdefault(prefix, ns)
        resolved = [f.path for f in files]
        return cls(
            backend=backend,
            engine=engine,
            names=tuple(p.stem for p in resolved),
            paths=tuple(resolved),
            prefixes=prefixes,
            etag=etag,
        )

    def query(self, sparql: str, *, row_limit: int = 1000, time_budget_s: float | None = None) -> QueryResult:
        """Run a SPARQL 1.1 query (SELECT/ASK/CONSTRUCT/DESCRIBE).

        At most ``row_limit`` rows (or triples) are returned; ``truncated``
        tells that more existed.  With ``time_budget_s``, the deadline is
        checked after every result and :class:`QueryTimeout` raised once it
        has passed (see the backends for what cannot be interrupted).
        Raises :class:`QuerySyntaxError`, :class:`UpdateRefused`,
        :class:`FeatureRefused` (``SERVICE``, ``FROM``), :class:`QueryTimeout`
        or :class:`QueryEvaluationError`.
        """
        if row_limit < 0:
            raise ValueError(f"row_limit must be >= 0, got {row_limit}")
        if time_budget_s is not None and time_budget_s < 0:
            raise ValueError(f"time_budget_s must be >= 0, got {time_budget_s}")
        feature = _refused_feature(sparql)
        if feature is not None:
            raise FeatureRefused(feature)
        return self._engine.query(sparql, row_limit, _Deadline(time_budget_s))
