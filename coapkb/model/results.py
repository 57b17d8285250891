"""Transport- and backend-neutral SPARQL query results.

Terms are rdflib terms (``URIRef``, ``Literal``, ``BNode``); ``None`` stands
for an unbound variable in a SELECT row.  Both knowledge-base backends
produce these, and every codec (compact CBOR, SPARQL 1.1 JSON) reads and
writes them, so a round trip through any codec is checked against them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from rdflib.term import BNode, Literal, URIRef

Term = URIRef | Literal | BNode
Row = tuple[Term | None, ...]
Triple = tuple[Term, Term, Term]


@dataclass(frozen=True)
class SelectResult:
    """Solutions of a SELECT query, one tuple per row in ``variables`` order."""

    variables: tuple[str, ...]
    rows: tuple[Row, ...]
    #: True when the server stopped at its row limit: more solutions exist.
    truncated: bool = False

    def __post_init__(self) -> None:
        for row in self.rows:
            if len(row) != len(self.variables):
                raise ValueError(f"row has {len(row)} values for {len(self.variables)} variables")

    def as_dicts(self) -> list[dict[str, Term]]:
        """Rows as ``{variable: term}``, unbound variables left out."""
        return [{v: t for v, t in zip(self.variables, row) if t is not None} for row in self.rows]


@dataclass(frozen=True)
class AskResult:
    """The boolean answer of an ASK query."""

    value: bool


@dataclass(frozen=True)
class GraphResult:
    """Triples of a CONSTRUCT or DESCRIBE query."""

    triples: tuple[Triple, ...] = field(default_factory=tuple)
    truncated: bool = False


QueryResult = SelectResult | AskResult | GraphResult
