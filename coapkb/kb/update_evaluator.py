"""A SPARQL Update run over a writable knowledge base's view: the triples
it removes and adds.

Its operations (split by :mod:`.update`) run in order, each seeing the
ones before: their changes go into the view for the next one to read, and
are taken back before the write is made, since the replicas decide the
view (:class:`~coapkb.kb.live.LiveKB`).  A write may change at most
:attr:`~coapkb.kb.live.WriteLimits.max_triples` triples each way.
"""

from __future__ import annotations

from rdflib.term import BNode, Literal, URIRef

from ..model.results import GraphResult, Triple
from .errors import KBError, QueryEvaluationError
from .limits import Deadline
from .oxigraph_backend import OxigraphBackend
from .update import Operation, ParsedUpdate, UpdateUnsupported
from .view import View, as_quad

__all__ = ["UpdateEvaluator", "WriteTooLarge", "check_term_kinds"]


class WriteTooLarge(KBError):
    """A write that would change more triples than a robot takes at once (4.13)."""


class UpdateEvaluator:
    """Turns a parsed update into the triples it removes and adds at ``view``
    (see the module docstring)."""

    def __init__(self, view: View, max_triples: int) -> None:
        self.view = view
        self.max_triples = max_triples

    def changes(self, parsed: ParsedUpdate) -> tuple[list[Triple], list[Triple]]:
        """The triples ``parsed`` removes and adds, in the order first named."""
        removes: dict[Triple, None] = {}
        adds: dict[Triple, None] = {}
        undo: list[tuple[str, Triple]] = []
        try:
            for operation in parsed.operations:
                gone, new = self._resolve(operation, parsed.prologue)
                for triple in gone:
                    adds.pop(triple, None)
                    removes[triple] = None
                for triple in new:
                    removes.pop(triple, None)
                    adds[triple] = None
                if operation is not parsed.operations[-1]:
                    undo += self.view.scratch(gone, new)
        finally:
            self.view.unscratch(undo)
        return list(removes), list(adds)

    def _resolve(self, operation: Operation, prologue: str) -> tuple[list[Triple], list[Triple]]:
        removes_q, adds_q = operation.queries(prologue)
        removed = self._construct(removes_q, operation.reads_module)
        if operation.kind == "DELETE DATA":
            view = self.view.writable()
            removed = [t for t in removed if as_quad(t) in view]
        added = self._construct(adds_q, operation.reads_module)
        for triple in added:
            check_term_kinds(triple)
        return removed, added

    def _construct(self, query: str | None, reads_module: bool) -> list[Triple]:
        if query is None:
            return []
        limit = self.max_triples
        if reads_module:
            result = self.view.query(query, row_limit=limit, time_budget_s=2.0)
        else:
            result = OxigraphBackend().query(query, limit, Deadline(None))
        if not isinstance(result, GraphResult):  # pragma: no cover - a CONSTRUCT always gives a graph
            raise QueryEvaluationError("a write's template did not give triples")
        if result.truncated:
            raise WriteTooLarge(f"the update changes more than {limit} triples; split it")
        return list(result.triples)


def check_term_kinds(triple: Triple) -> None:
    """Refuse what a write cannot carry: blank nodes, a literal subject or predicate."""
    s, p, o = triple
    if any(isinstance(t, BNode) for t in triple):
        raise UpdateUnsupported("blank nodes cannot be written: they have no identity across robots; use an IRI")
    if not isinstance(s, URIRef) or not isinstance(p, URIRef) or not isinstance(o, (URIRef, Literal)):
        raise UpdateUnsupported("a triple is an IRI subject, an IRI predicate and an IRI or literal object")
