"""A robot's knowledge base that learns: its modules' files, the writes
every holder made since, and the graph queries see.

The files' graph stays as loaded: it is the base every holder shares, and
tells a write which triples came from the files.  The first write copies
it into the *view* (:mod:`.view`), the graph queries run on from then on;
every change (a local write or a teammate's delta) goes into the module's
:class:`~coapkb.kb.replica.Replica` first and into the view as the effect
the replica computes, so the view is always what the replicas say.  An
update's text becomes the triples it changes in :mod:`.update_evaluator`,
and :mod:`.pinned_answers` keeps each task's answers as first given.

A triple belongs to the module whose namespace its subject is in
(``vocabulary.ONTOLOGIES``; the ontology's own IRI too).  A robot holding a
single module takes every other subject into it.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import pyoxigraph as ox
from rdflib.term import URIRef

from ..model.deltas import Delta, MadeUnder, WrittenState
from ..model.results import QueryResult, Term, Triple
from ..typed_fields import require_at_least
from ..world.vocabulary import ONTOLOGIES, SINGLE_VALUED
from .errors import KBError
from .files_graph import files_graph
from .oxigraph_backend import OxigraphBackend
from .pinned_answers import PINNED_ANSWERS, PinnedAnswers
from .replica import Effect, Replica, ReplicaLimits
from .store import KnowledgeBase
from .update import UpdateUnsupported, parse_update
from .update_evaluator import UpdateEvaluator, WriteTooLarge, check_term_kinds
from .view import View, as_quad
from .write_ids import Remembered, WriteId, WriteIds, WriteTag

__all__ = ["Keeping", "LiveKB", "NotHeld", "PreconditionFailed", "WriteLimits", "WriteTooLarge", "Written"]


class NotHeld(KBError):
    """The write names a module this robot does not hold."""

    def __init__(self, module: str, held: Iterable[str], holders: Iterable[str] = ()) -> None:
        self.module = module
        elsewhere = ", ".join(holders)
        where = f"; write it to a robot that does: {elsewhere}" if elsewhere else ""
        super().__init__(f"this robot does not hold the {module} module (it holds {', '.join(held)}){where}")


class PreconditionFailed(KBError):
    """An If-Match that no longer matches the module's version (4.12)."""


@dataclass(frozen=True)
class WriteLimits:
    """What one write may do."""

    #: Triples one write may remove or add (each CONSTRUCT is stopped there).
    max_triples: int = 1000
    replica: ReplicaLimits = field(default_factory=ReplicaLimits)
    #: Write ids remembered per writer (:mod:`.write_ids`): a repeat comes
    #: within seconds, and a robot writes a few times a task.
    ids_per_writer: int = 64
    #: Writers whose ids are remembered: a team's robots, their earlier
    #: incarnations and a few operators.
    id_writers: int = 256
    #: Adds and removes the view's store takes, at least (four times its size
    #: if more), before it is copied afresh.  pyoxigraph's in-memory store
    #: keeps memory for every value and version it ever held (measured: about
    #: 0.3 kB per add and remove of a new value, never given back), so a long
    #: shift's positions and picks would grow a robot without end; a copy
    #: holds only what is live (20 ms for the shipped Location and Capability
    #: KBs, 15,000 triples).
    rebuild_after_changes: int = 200_000

    def __post_init__(self) -> None:
        require_at_least(self, ("max_triples", "ids_per_writer", "id_writers", "rebuild_after_changes"))


@dataclass(frozen=True)
class Written:
    """A local write: the delta per module it changed, and its new version."""

    deltas: Mapping[str, Delta]
    version: bytes
    removed: int
    added: int
    #: The id it was made under (pushed with its deltas).
    tag: WriteTag | None = None

    @property
    def made(self) -> MadeUnder | None:
        """Its id as its pushes carry it."""
        if self.tag is None:
            return None
        wid = self.tag.wid
        return MadeUnder(wid.peer, wid.writer, wid.write, self.tag.digest, self.removed, self.added)


class Keeping(Protocol):
    """What keeps a LiveKB's changes (a data folder: :class:`~.durable.Keeper`):
    the changes its replicas took, and the id a local write was made under."""

    def __call__(self, changes: Sequence[tuple[str, Sequence[Delta] | WrittenState]],
                 made: tuple[WriteId, Remembered] | None = None) -> None: ...


def wall_ms() -> int:
    """The machine's wall clock in milliseconds: a write's stamp (the
    hybrid logical clock keeps stamps growing if it steps back)."""
    return time.time_ns() // 1_000_000


def module_namespaces(names: Iterable[str]) -> dict[str, tuple[str, ...]]:
    """Module name -> the IRI prefixes of the subjects it holds."""
    return {name: (ONTOLOGIES[name][1], ONTOLOGIES[name][0]) for name in names if name in ONTOLOGIES}


class LiveKB:
    """The modules of one robot as they stand now (see the module docstring).

    Answers queries like a :class:`KnowledgeBase` (``names``, ``prefixes``,
    ``etag``, ``query``); writes with :meth:`update` and :meth:`patch`,
    joins teammates' changes with :meth:`apply` and :meth:`join`."""

    def __init__(
        self,
        base: KnowledgeBase,
        writer: str,
        *,
        wall_ms: Callable[[], int],
        limits: WriteLimits | None = None,
        single_valued: frozenset[str] = SINGLE_VALUED,
        holders: Mapping[str, Sequence[str]] | None = None,
        pinned_answers: int = PINNED_ANSWERS,
    ) -> None:
        if base.backend != "oxigraph" or not isinstance(base.engine, OxigraphBackend) or base.engine.on_disk:
            raise ValueError("a writable knowledge base needs the in-memory oxigraph backend")
        self.base = base
        self.names = base.names
        self.prefixes = base.prefixes
        self.backend = base.backend
        self.writer = writer
        self.limits = limits or WriteLimits()
        self._wall_ms = wall_ms
        #: What the files say, as writes and joins ask (shared by robots loading ``base``).
        self._files = files_graph(base)
        #: The graph queries see: the files', then what the replicas say.
        self.view = View(base, self._files, self.limits.rebuild_after_changes)
        self._evaluator = UpdateEvaluator(self.view, self.limits.max_triples)
        functional = frozenset(URIRef(p) for p in single_valued) | declared_functional(self.view.base_store)
        self.replicas: dict[str, Replica] = {
            name: Replica(writer, single_valued=functional, base_values=self._files.values, limits=self.limits.replica)
            for name in base.names
        }
        self._namespaces = module_namespaces(base.names)
        #: module -> the robots known to hold it (named when a write is misdirected)
        self.holders = dict(holders or {})
        self._etag: bytes | None = None
        #: Called with the modules a change touched (after the view has it).
        self.listeners: list[Callable[[frozenset[str]], None]] = []
        #: The answers first given for each task (:meth:`query_at`).
        self.pinned = PinnedAnswers(pinned_answers)
        #: Told every change the replicas took, before anyone hears of it
        #: (a data folder: :mod:`.durable`); None: kept in memory only.
        self.keeper: Keeping | None = None
        #: The ids of the writes made lately, and what each was answered.
        self.write_ids = WriteIds(self.limits.ids_per_writer, self.limits.id_writers)

    def __repr__(self) -> str:
        return f"<LiveKB {'+'.join(self.names)} of {self.writer}>"

    # -------------------------------------------------------------- reading

    @property
    def triple_count(self) -> int:
        return self.view.triple_count

    @property
    def rebuilds(self) -> int:
        """Times the view was copied afresh (:attr:`WriteLimits.rebuild_after_changes`)."""
        return self.view.rebuilds

    @property
    def etag(self) -> bytes:
        """The version: the files' ETag and every change the replicas hold,
        so two holders that agree give the same ETag."""
        if self._etag is None:
            digest = hashlib.blake2b(self.base.etag, digest_size=8)
            for name in self.names:
                digest.update(repr((name, self.replicas[name].context.summary())).encode())
            untouched = not any(r.context.vv or r.context.cloud for r in self.replicas.values())
            self._etag = self.base.etag if untouched else digest.digest()
        return self._etag

    @property
    def changed(self) -> bool:
        return self.view.changed

    def module_version(self, module: str) -> bytes:
        return hashlib.blake2b(repr(self.replicas[module].context.summary()).encode(), digest_size=8).digest()

    def query(self, sparql: str, *, row_limit: int = 1000, time_budget_s: float | None = None) -> QueryResult:
        return self.view.query(sparql, row_limit=row_limit, time_budget_s=time_budget_s)

    def query_at(self, task: int, sparql: str) -> QueryResult:
        """``query``'s answer as it was when first asked for ``task``.

        A decision must read the same knowledge on every robot of a cluster,
        though a write may land between two robots' questions: the holder
        they all ask answers each question of one task alike
        (docs/knowledge.md, "The world in the KB").  The last
        ``pinned_answers`` questions are kept."""
        return self.pinned.answer(task, sparql, self.query)

    def _is_base(self, triple: Triple) -> bool:
        return self._files.has(triple)

    def module_of(self, triple: Triple) -> str:
        """The module a triple belongs to: its subject's namespace (module docstring)."""
        subject = str(triple[0])
        for name, prefixes in self._namespaces.items():
            if any(subject.startswith(prefix) for prefix in prefixes):
                return name
        for name, (ontology, ns, _) in ONTOLOGIES.items():
            if subject.startswith(ns) or subject == ontology:
                raise NotHeld(name, self.names, self.holders.get(name, ()))
        if len(self.names) == 1:
            return self.names[0]
        known = ", ".join(f"{ns} ({name})" for name, (_, ns, _) in ONTOLOGIES.items())
        raise UpdateUnsupported(f"subject {subject} is in no module's namespace: {known}")

    # -------------------------------------------------------------- writing

    def update(self, text: str, *, if_match: tuple[bytes, ...] = (), tag: WriteTag | None = None) -> Written:
        """Run SPARQL 1.1 Update text (see :mod:`.update`) as one write;
        ``tag``: its id, remembered in :attr:`write_ids` (and on disk with
        the write) once it is made.  A repeat is the caller's to catch."""
        parsed = parse_update(text)
        self._check_precondition(if_match)
        removes, adds = self._evaluator.changes(parsed)
        return self._write(removes, adds, tag)

    def patch(self, deletes: Iterable[Triple], inserts: Iterable[Triple], *, if_match: tuple[bytes, ...] = (),
              tag: WriteTag | None = None) -> Written:
        """A compact patch: remove ``deletes`` that are there, add ``inserts``
        (``tag``: as :meth:`update`'s)."""
        self._check_precondition(if_match)
        deletes, inserts = list(deletes), list(inserts)
        for triple in deletes + inserts:
            check_term_kinds(triple)
        if len(deletes) > self.limits.max_triples or len(inserts) > self.limits.max_triples:
            raise WriteTooLarge(f"a write changes at most {self.limits.max_triples} triples each way")
        view = self.view.writable()
        return self._write([t for t in deletes if as_quad(t) in view], inserts, tag)

    def _check_precondition(self, if_match: tuple[bytes, ...]) -> None:
        # An empty If-Match asks only that the resource exist: it does.
        if if_match and b"" not in if_match and self.etag not in if_match:
            raise PreconditionFailed(f"the knowledge base is at version {self.etag.hex()}, not {if_match[0].hex()}")

    def _write(self, removes: list[Triple], adds: list[Triple], tag: WriteTag | None = None) -> Written:
        by_module: dict[str, tuple[list[Triple], list[Triple]]] = {}
        for triple in removes:
            by_module.setdefault(self.module_of(triple), ([], []))[0].append(triple)
        for triple in adds:
            by_module.setdefault(self.module_of(triple), ([], []))[1].append(triple)
        deltas: dict[str, Delta] = {}
        now = self._wall_ms()
        removed = added = 0
        try:
            for module, (gone, new) in by_module.items():
                replica = self.replicas[module]
                if replica.unchanged_by(gone, new, self._is_base):
                    continue  # nothing to change: no delta, the version stays
                delta, effect = replica.write(gone, new, now, self._is_base)
                deltas[module] = delta
                added += len(delta.added)
                removed += len(effect.removed)
                self._show(effect)
        except BaseException:
            # What was written is kept, even if a later module refused its part.
            if self.keeper is not None and deltas:
                self.keeper([(module, [delta]) for module, delta in deltas.items()])
            raise
        self._etag = None
        written = Written(deltas, self.etag, removed, added, tag)
        made = None
        if tag is not None:
            # Even a write that changed nothing: a repeat after a later change would.
            made = (tag.wid, Remembered(tag.digest, written.version, removed, added))
            self.write_ids.remember(*made)
        if self.keeper is not None and (deltas or made is not None):
            # One record each, fsynced together: the id is on disk with its write.
            self.keeper([(module, [delta]) for module, delta in deltas.items()], made)
        self._changed(frozenset(deltas))
        return written

    def continue_as(self, writer: str) -> None:
        """Write from now on as ``writer`` in every module, the name of this
        robot's lives (:meth:`Replica.continue_as`; when: :mod:`.life_fence`).

        Raises :class:`ValueError` with a data folder (its writer is the
        folder's) or once this robot's writer has a dot."""
        if self.keeper is not None:
            raise ValueError(f"{self.writer} writes as its data folder's writer")
        if self.has_written:
            raise ValueError(f"{self.writer} has written: it cannot write as {writer}")
        for replica in self.replicas.values():
            replica.continue_as(writer)
        self.writer = writer

    @property
    def has_written(self) -> bool:
        """A dot under this robot's writer is known in some module."""
        return any(replica.has_written for replica in self.replicas.values())

    # -------------------------------------------------------------- joining

    def apply(self, module: str, deltas: Iterable[Delta], made: MadeUnder | None = None,
              made_by: str | None = None) -> bool:
        """Join teammates' deltas of ``module``; whether the view changed.
        ``made``: the id of the client's write the one delta came from, at
        the holder ``made_by``; remembered once the delta is here, so that
        a try of that write sent here next is a repeat (docs/knowledge.md,
        "A write tried again")."""
        replica = self.replicas[module]
        changed = False
        taken: list[Delta] = []
        deltas = list(deltas)
        for delta in deltas:
            new, refused = delta.dot not in replica.context, replica.refused
            effect = replica.apply(delta, self._is_base)
            if new and replica.refused == refused:
                taken.append(delta)
            changed |= bool(effect)
            self._show(effect)
        remembered = None
        if made is not None and deltas and all(d.dot in replica.context for d in deltas):
            wid = WriteId(made.peer, made.writer, made.write)
            if self.write_ids.get(wid) is None:
                self._etag = None
                remembered = (wid, Remembered(made.digest, self.etag, made.removed, made.added, made_by=made_by))
                self.write_ids.remember(*remembered)
        if (taken or remembered is not None) and self.keeper is not None:
            self.keeper([(module, taken)] if taken else [], remembered)
        self._changed(frozenset({module}) if changed else frozenset())
        return changed

    def join(self, module: str, state: WrittenState) -> bool:
        replica = self.replicas[module]
        new = not replica.context.covers(state.context) or not state.removed_base <= replica.removed_base
        effect = replica.join(state, self._is_base)
        if new and self.keeper is not None:
            self.keeper([(module, state)])
        self._show(effect)
        self._changed(frozenset({module}) if effect else frozenset())
        return bool(effect)

    def _show(self, effect: Effect) -> None:
        """The effect a replica computed, into the view."""
        self.view.show(effect)

    def _changed(self, modules: frozenset[str]) -> None:
        self._etag = None
        if modules:
            for listener in list(self.listeners):
                listener(modules)


_RDF_TYPE = ox.NamedNode("http://www.w3.org/1999/02/22-rdf-syntax-ns#type")
_OWL_FUNCTIONAL = ox.NamedNode("http://www.w3.org/2002/07/owl#FunctionalProperty")


def declared_functional(store: ox.Store) -> frozenset[Term]:
    """The properties the modules' files declare ``owl:FunctionalProperty``:
    single-valued like :data:`~coapkb.world.vocabulary.SINGLE_VALUED`.
    Every holder loads the same files, so every replica counts them alike."""
    return frozenset(URIRef(q.subject.value) for q in store.quads_for_pattern(None, _RDF_TYPE, _OWL_FUNCTIONAL)
                     if isinstance(q.subject, ox.NamedNode))

