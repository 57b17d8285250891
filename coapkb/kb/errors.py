"""The knowledge base's errors; every message is fit for a client."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from ..errors import CoapkbError

__all__ = [
    "FeatureRefused",
    "KBError",
    "KBLoadError",
    "QueryEvaluationError",
    "QueryRefused",
    "QuerySyntaxError",
    "QueryTimeout",
    "UnexpectedResult",
    "UpdateRefused",
    "short_message",
]


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


class UnexpectedResult(KBError):
    """A query answered with another kind of result than its caller reads
    (an ASK's answer or a graph where SELECT rows were wanted)."""


def short_message(exc: BaseException | str) -> str:
    """A parser's or store's message on one line, at most 300 characters."""
    text = " ".join(str(exc).split())
    return text if len(text) <= 300 else text[:297] + "..."
