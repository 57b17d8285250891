"""Writes to a module: SPARQL 1.1 Update text and the compact CBOR patch
(pure: parsing and encoding only; :mod:`.live` runs them).

A replicated module has one default graph and no identity for blank nodes
across robots, so of SPARQL 1.1 Update a robot takes the operations that
change triples of that graph: ``INSERT DATA``, ``DELETE DATA``,
``DELETE WHERE`` and ``DELETE {..} INSERT {..} WHERE {..}`` (either clause
alone too), separated by ``;``.  ``LOAD``, ``CLEAR``, ``CREATE``, ``DROP``,
``ADD``, ``MOVE``, ``COPY``, ``WITH``, ``USING``, ``GRAPH`` and ``SERVICE``
are refused as :class:`UpdateUnsupported` (4.22), as is a blank node in
what a write adds.

Each operation becomes CONSTRUCT queries over the module (its template,
the same syntax as a triples template, as the CONSTRUCT's template; its
pattern as the WHERE): a write is then a concrete set of triples removed
and added, which is what replicates.

The compact patch (content-format 60, ``docs/knowledge.cddl``)::

    patch = [deletes: graph-item, inserts: graph-item]
    graph-item = #6.24(bstr .cbor graph)   ; a compact-results graph
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import cbor2

from ..model.results import Triple
from ..wire import codec
from .errors import KBError, QuerySyntaxError

__all__ = [
    "Operation",
    "ParsedUpdate",
    "UpdateUnsupported",
    "decode_patch",
    "encode_patch",
    "parse_update",
]


class UpdateUnsupported(KBError):
    """Valid SPARQL Update that a replicated module does not take (4.22)."""


@dataclass(frozen=True)
class Operation:
    """One operation: its kind and its parts' text (without braces)."""

    kind: str  # "INSERT DATA", "DELETE DATA", "DELETE WHERE" or "MODIFY"
    delete: str | None = None
    insert: str | None = None
    where: str | None = None

    def queries(self, prologue: str) -> tuple[str | None, str | None]:
        """CONSTRUCT queries for what it removes and what it adds (None: nothing)."""
        if self.kind in ("INSERT DATA", "DELETE DATA"):
            data = self.insert if self.kind == "INSERT DATA" else self.delete
            query = f"{prologue}\nCONSTRUCT {{\n{data}\n}} WHERE {{}}"
            return (None, query) if self.kind == "INSERT DATA" else (query, None)
        if self.kind == "DELETE WHERE":
            return f"{prologue}\nCONSTRUCT {{\n{self.where}\n}} WHERE {{\n{self.where}\n}}", None
        removes = None if self.delete is None else f"{prologue}\nCONSTRUCT {{\n{self.delete}\n}} WHERE {{\n{self.where}\n}}"
        adds = None if self.insert is None else f"{prologue}\nCONSTRUCT {{\n{self.insert}\n}} WHERE {{\n{self.where}\n}}"
        return removes, adds

    @property
    def reads_module(self) -> bool:
        """Whether it matches against the module (DATA operations do not)."""
        return self.kind not in ("INSERT DATA", "DELETE DATA")


@dataclass(frozen=True)
class ParsedUpdate:
    prologue: str
    operations: tuple[Operation, ...]


_TOKEN = re.compile(
    r'(?P<str>"""(?:[^"\\]|\\.|"(?!""))*"""'
    r"|'''(?:[^'\\]|\\.|'(?!''))*'''"
    r'|"(?:[^"\\\n]|\\.)*"'
    r"|'(?:[^'\\\n]|\\.)*')"
    r'|(?P<iri><[^<>"{}|^`\\\s]*>)'
    r"|(?P<comment>\#[^\n]*)"
    r"|(?P<var>[?$]\w+)"
    # a keyword, or a prefixed name (the empty prefix too: ":Robot1")
    r"|(?P<word>(?:[A-Za-z_][\w.-]*)?:[\w.:-]*|[A-Za-z_][\w.-]*)"
    r"|(?P<punct>[{};])"
    r"|(?P<space>\s+)"
    r"|(?P<other>.)",
    re.DOTALL,
)

_UNSUPPORTED = {
    "LOAD": "LOAD would fetch from the network",
    "CLEAR": "CLEAR would empty the module on every holder; delete the triples instead",
    "DROP": "DROP works on named graphs; a module is one default graph",
    "CREATE": "CREATE works on named graphs; a module is one default graph",
    "ADD": "ADD works on named graphs; a module is one default graph",
    "MOVE": "MOVE works on named graphs; a module is one default graph",
    "COPY": "COPY works on named graphs; a module is one default graph",
    "WITH": "WITH names a graph; a module is one default graph",
    "USING": "USING names a graph; a module is one default graph",
    "GRAPH": "GRAPH names a graph; a module is one default graph",
    "SERVICE": "SERVICE would query another endpoint: a write reads this module only",
}


class _Scanner:
    """Splits update text into its prologue and operations (no validation
    of what lies inside braces: the store's parser does that)."""

    def __init__(self, text: str) -> None:
        self.text = text
        self.tokens = [(m.lastgroup, m.group(), m.start()) for m in _TOKEN.finditer(text)]
        self.tokens = [t for t in self.tokens if t[0] not in ("space", "comment")]
        self.i = 0

    def peek_word(self) -> str | None:
        """The keyword here, upper-cased (a prefixed name is none)."""
        if self.i < len(self.tokens) and self.tokens[self.i][0] == "word" and ":" not in self.tokens[self.i][1]:
            return self.tokens[self.i][1].upper()
        return None

    def take_word(self, *expected: str) -> str:
        word = self.peek_word()
        if word is None or (expected and word not in expected):
            raise ValueError
        self.i += 1
        return word

    def block(self) -> str:
        """The text inside the braces that start here."""
        if self.i >= len(self.tokens) or self.tokens[self.i][1] != "{":
            raise ValueError
        start = self.tokens[self.i][2] + 1
        depth = 0
        while self.i < len(self.tokens):
            kind, value, pos = self.tokens[self.i]
            self.i += 1
            if kind == "word" and ":" not in value and value.upper() in ("GRAPH", "SERVICE"):
                raise UpdateUnsupported(f"{value.upper()}: {_UNSUPPORTED[value.upper()]}")
            if value == "{":
                depth += 1
            elif value == "}":
                depth -= 1
                if depth == 0:
                    return self.text[start:pos]
        raise ValueError

    def prologue_item(self) -> str:
        start = self.tokens[self.i][2]
        word = self.take_word("PREFIX", "BASE")
        if word == "PREFIX":  # the prefix name, "obj:" or ":"
            if self.i >= len(self.tokens) or not self.tokens[self.i][1].endswith(":"):
                raise ValueError
            self.i += 1
        if self.i >= len(self.tokens) or self.tokens[self.i][0] != "iri":
            raise ValueError
        end = self.tokens[self.i][2] + len(self.tokens[self.i][1])
        self.i += 1
        return self.text[start:end]

    def operation(self) -> Operation:
        word = self.peek_word()
        if word in _UNSUPPORTED:
            raise UpdateUnsupported(f"{word}: {_UNSUPPORTED[word]}")
        word = self.take_word("INSERT", "DELETE")
        if self.peek_word() == "DATA":
            self.i += 1
            data = self.block()
            return Operation("INSERT DATA", insert=data) if word == "INSERT" else Operation("DELETE DATA", delete=data)
        if word == "DELETE" and self.peek_word() == "WHERE":
            self.i += 1
            return Operation("DELETE WHERE", where=self.block())
        delete = insert = None
        if word == "DELETE":
            delete = self.block()
            if self.peek_word() == "INSERT":
                self.i += 1
                insert = self.block()
        else:
            insert = self.block()
        if self.peek_word() in _UNSUPPORTED:
            raise UpdateUnsupported(f"{self.peek_word()}: {_UNSUPPORTED[self.peek_word() or '']}")
        self.take_word("WHERE")
        return Operation("MODIFY", delete=delete, insert=insert, where=self.block())

    def parse(self) -> ParsedUpdate:
        prologue: list[str] = []
        operations: list[Operation] = []
        while self.i < len(self.tokens):
            if self.peek_word() in ("PREFIX", "BASE"):
                prologue.append(self.prologue_item())
                continue
            operations.append(self.operation())
            if self.i < len(self.tokens):
                if self.tokens[self.i][1] != ";":
                    raise ValueError
                self.i += 1
        return ParsedUpdate("\n".join(prologue), tuple(operations))


_REFUSED_ANYWHERE = re.compile(r"\b(LOAD|SERVICE|GRAPH|WITH|USING|CLEAR|DROP)\b", re.IGNORECASE)


def parse_update(text: str) -> ParsedUpdate:
    """Split SPARQL 1.1 Update text into its prologue and operations.

    Raises :class:`UpdateUnsupported` for what a replicated module does not
    take and :class:`QuerySyntaxError` (with line and column) for text that
    is not SPARQL Update; the syntax is checked by Oxigraph's parser on an
    empty store, never on the module."""
    try:
        parsed = _Scanner(text).parse()
    except ValueError:
        parsed = None
    if parsed is None:
        # Not split: something is malformed.  A refused keyword is named
        # first; the store's parser is never given one (LOAD fetches).
        for kind, value, _ in _Scanner(text).tokens:
            if kind == "word" and _REFUSED_ANYWHERE.fullmatch(value):
                raise UpdateUnsupported(f"{value.upper()}: {_UNSUPPORTED[value.upper()]}")
    _check_syntax(text)
    if parsed is None:
        raise UpdateUnsupported("only INSERT DATA, DELETE DATA, DELETE WHERE and DELETE/INSERT ... WHERE are taken")
    if not parsed.operations:
        raise QuerySyntaxError("the update has no operation")
    return parsed


def _check_syntax(text: str) -> None:
    import pyoxigraph as ox

    from .oxigraph_backend import UPDATE_FORMS, syntax_error

    try:
        ox.Store().update(text)
    except SyntaxError as exc:
        raise syntax_error(str(exc), text, UPDATE_FORMS) from None
    except Exception:  # noqa: BLE001 - an evaluation error on an empty store: the syntax is fine
        pass


# ------------------------------------------------------------ compact patch


def encode_patch(deletes: Sequence[Triple], inserts: Sequence[Triple]) -> bytes:
    """The compact CBOR patch of a write (content-format 60)."""
    return cbor2.dumps([codec.graph_item(deletes), codec.graph_item(inserts)])


def decode_patch(data: bytes) -> tuple[tuple[Triple, ...], tuple[Triple, ...]]:
    """(deletes, inserts) of a compact patch; raises :class:`codec.CodecError`."""
    item = codec.load_cbor(data)
    if not isinstance(item, list) or len(item) != 2:
        raise codec.CodecError("a patch is [deletes, inserts]")
    return codec.decode_graph_item(item[0], "deletes"), codec.decode_graph_item(item[1], "inserts")
