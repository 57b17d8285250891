"""The graph a writable knowledge base answers queries from: its *view*.

Until the first change the files' graph serves queries (in the simulator
it stays shared by every robot loading it).  The first change copies it;
from then on every effect the replicas compute goes into the copy
(:class:`~coapkb.kb.live.LiveKB` decides what), so the view is always what
the replicas say.  pyoxigraph's in-memory store never gives back what it
once held, so a copy that took many adds and removes is copied afresh.
"""

from __future__ import annotations

import pyoxigraph as ox

from ..model.results import QueryResult, Triple
from .files_graph import FilesGraph
from .oxigraph_backend import OxigraphBackend, _to_ox
from .replica import Effect
from .store import KnowledgeBase

__all__ = ["View", "as_quad"]


class View:
    """The files' graph, then its copy kept in step with the replicas (see
    the module docstring); ``rebuild_after_changes``: adds and removes the
    copy takes, at least, before it is copied afresh
    (:attr:`~coapkb.kb.live.WriteLimits.rebuild_after_changes`)."""

    def __init__(self, base: KnowledgeBase, files: FilesGraph, rebuild_after_changes: int) -> None:
        assert isinstance(base.engine, OxigraphBackend)  # LiveKB takes no other
        self.base = base
        self.base_store: ox.Store = base.engine.store
        self._files = files
        self._rebuild_after_changes = rebuild_after_changes
        self._copy: OxigraphBackend | None = None
        #: Adds and removes the copy took since it was last copied afresh,
        #: and how many it may take before the next copy (its size is
        #: counted only then: counting a pyoxigraph store walks it).
        self._churn = 0
        self._churn_allowed = rebuild_after_changes
        #: Times the copy was copied afresh.
        self.rebuilds = 0

    @property
    def changed(self) -> bool:
        """Whether the files' graph was copied: something was written or joined."""
        return self._copy is not None

    @property
    def triple_count(self) -> int:
        return len(self._copy.store) if self._copy is not None else self.base.triple_count

    @property
    def store(self) -> ox.Store:
        """The store that answers queries now (the files' until the first change)."""
        return self._copy.store if self._copy is not None else self.base_store

    def query(self, sparql: str, *, row_limit: int = 1000, time_budget_s: float | None = None) -> QueryResult:
        if self._copy is None:
            return self.base.query(sparql, row_limit=row_limit, time_budget_s=time_budget_s)
        return self.base.query_with(self._copy, sparql, row_limit=row_limit, time_budget_s=time_budget_s)

    def writable(self) -> ox.Store:
        """The copy's store, made at the first call."""
        if self._copy is None:
            # Copy on first write: until then the files' graph serves queries
            # (and in the simulator stays shared by every robot loading it).
            view = ox.Store()
            view.extend(self._files.quads())
            self._copy = OxigraphBackend(view)
        return self._copy.store

    def show(self, effect: Effect) -> None:
        """Put a replica's effect into the view."""
        if not effect:
            return
        store = self.writable()
        for triple in effect.removed:
            store.remove(as_quad(triple))
        if effect.added:
            # At once: a join at a restart may add 100,000.
            store.extend(as_quad(triple) for triple in effect.added)
        self._churn += len(effect.removed) + len(effect.added)
        if self._churn >= self._churn_allowed:
            fresh = ox.Store()
            fresh.extend(store.quads_for_pattern(None, None, None))
            self._copy = OxigraphBackend(fresh)
            self._churn = 0
            self._churn_allowed = max(self._rebuild_after_changes, 4 * len(fresh))
            self.rebuilds += 1

    def scratch(self, removes: list[Triple], adds: list[Triple]) -> list[tuple[str, Triple]]:
        """Remove and add triples for a moment (an update's operation, for
        the next one to read); what :meth:`unscratch` takes back."""
        store = self.writable()
        undo: list[tuple[str, Triple]] = []
        for triple in removes:
            if as_quad(triple) in store:
                store.remove(as_quad(triple))
                undo.append(("add", triple))
        for triple in adds:
            if as_quad(triple) not in store:
                store.add(as_quad(triple))
                undo.append(("remove", triple))
        self._churn += len(undo)
        return undo

    def unscratch(self, undo: list[tuple[str, Triple]]) -> None:
        store = self.writable() if undo else None
        for action, triple in reversed(undo):
            assert store is not None
            (store.add if action == "add" else store.remove)(as_quad(triple))
        self._churn += len(undo)


def as_quad(triple: Triple) -> ox.Quad:
    s, p, o = triple
    return ox.Quad(_to_ox(s), _to_ox(p), _to_ox(o))  # type: ignore[arg-type]  # positions checked on the way in
