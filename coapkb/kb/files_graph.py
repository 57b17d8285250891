"""What a knowledge base's files say, as a write or a join asks it.

Every triple a write or a join touches is asked about twice: whether it came
from the files, and (for a single-valued property) which values the files
give its subject.  The files' graph never changes, so both answers are kept:
a set of its triples (a restart joining 100,000 written triples turned each
into pyoxigraph's terms twice without it) and the values once asked.  One
:class:`FilesGraph` per loaded KB, shared by every robot that loads it (the
simulator's robots of one process share their KBs).
"""

from __future__ import annotations

import weakref

import pyoxigraph as ox

from ..model.results import Term, Triple
from .oxigraph_backend import OxigraphBackend, _from_ox, _to_ox
from .store import KnowledgeBase

__all__ = ["FilesGraph", "files_graph"]


class FilesGraph:
    """The default graph of ``base``'s files, asked by triple and by (subject, predicate)."""

    #: (subject, predicate) pairs whose values are kept before the memo
    #: starts afresh: a bound, not a tuning (a warehouse's single-valued
    #: properties number a few thousand).
    MAX_KEPT_VALUES = 100_000

    def __init__(self, base: KnowledgeBase) -> None:
        assert isinstance(base.engine, OxigraphBackend)  # LiveKB takes no other
        self._store: ox.Store = base.engine.store
        self._triples: frozenset[Triple] | None = None
        self._quads: list[ox.Quad] | None = None
        self._values: dict[tuple[Term, Term], tuple[Term, ...]] = {}

    def has(self, triple: Triple) -> bool:
        """Whether ``triple`` is one of the files' (built at the first question)."""
        if self._triples is None:
            # Each term converted once: the files name a few thousand terms
            # in tens of thousands of triples (3x faster to build).
            terms: dict[object, Term] = {}

            def convert(term: object) -> Term:
                found = terms.get(term)
                if found is None:
                    found = terms[term] = _from_ox(term)
                return found

            quads = self._store.quads_for_pattern(None, None, None, ox.DefaultGraph())
            self._triples = frozenset((convert(q.subject), convert(q.predicate), convert(q.object)) for q in quads)
        return triple in self._triples

    def quads(self) -> list[ox.Quad]:
        """Every quad of the files, listed at the first call: what a view's
        first change copies.  pyoxigraph copies a list 1.4x faster than a
        store, and the simulator's robots copy the same files thousands of
        times a scan."""
        if self._quads is None:
            self._quads = list(self._store)
        return self._quads

    def values(self, s: Term, p: Term) -> tuple[Term, ...]:
        """The files' objects of ``s p``, in the store's order."""
        key = (s, p)
        kept = self._values.get(key)
        if kept is None:
            pattern = self._store.quads_for_pattern(_to_ox(s), _to_ox(p), None)  # type: ignore[arg-type]  # s, p: never literals
            kept = tuple(_from_ox(q.object) for q in pattern)
            if len(self._values) >= self.MAX_KEPT_VALUES:
                self._values.clear()
            self._values[key] = kept
        return kept


_FILES_GRAPHS: weakref.WeakKeyDictionary[KnowledgeBase, FilesGraph] = weakref.WeakKeyDictionary()


def files_graph(base: KnowledgeBase) -> FilesGraph:
    """``base``'s :class:`FilesGraph`, made at the first call and shared after."""
    graph = _FILES_GRAPHS.get(base)
    if graph is None:
        graph = _FILES_GRAPHS[base] = FilesGraph(base)
    return graph
