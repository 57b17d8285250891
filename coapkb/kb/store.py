"""A robot's read-only knowledge base: RDF files answering SPARQL queries.

Two interchangeable backends give identical :mod:`coapkb.model.results`:

* ``"oxigraph"`` (default, :mod:`.oxigraph_backend`): a pyoxigraph in-memory
  ``Store``, or an on-disk index (:mod:`.index`).  About 0.03 ms per lookup
  query, flat in the KB size, and ~20x faster loading than rdflib
  (``docs/reports/2026-11-22-performance-anchors.md``, section 1).
* ``"rdflib"`` (:mod:`.rdflib_backend`): a plain ``rdflib.Graph``, the seed
  paper's library.  Parsing a query string costs ~3 ms, so prepared queries
  are cached by query text.

A KB is the files as loaded, read-only: SPARQL Update sent as a query is
refused (:mod:`.refusals`); a writable module wraps it (:mod:`.live`).
Every query runs under a row limit and an optional time budget
(:mod:`.limits`), so one request cannot starve a robot.  Files and their formats:
:mod:`.formats`; errors: :mod:`.errors`.
"""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Protocol

import pyoxigraph as ox

from ..model.results import QueryResult, Term
from .errors import FeatureRefused
from .formats import KBFile
from .index import open_or_build_index
from .limits import Deadline
from .named_queries import NAMED_QUERIES
from .oxigraph_backend import OxigraphBackend
from .refusals import refused_feature
from .results import expect_select

__all__ = ["BACKENDS", "KnowledgeBase", "named_rows"]

BACKENDS = ("oxigraph", "rdflib")


class QueryableKB(Protocol):
    """What answering needs of a KB: a :class:`~.store.KnowledgeBase` or a :class:`~.live.LiveKB`."""

    names: tuple[str, ...]
    backend: str
    prefixes: dict[str, str]

    @property
    def triple_count(self) -> int: ...

    @property
    def etag(self) -> bytes: ...

    def query(self, sparql: str, *, row_limit: int = 1000, time_budget_s: float | None = None) -> QueryResult: ...


class Backend(Protocol):
    """What :class:`KnowledgeBase` needs of a backend."""

    #: whether :meth:`load` may run for several files at once, on threads
    parallel_load: bool

    @property
    def triple_count(self) -> int: ...

    def load(self, path: Path, fmt: str) -> None: ...

    def query(self, text: str, row_limit: int, deadline: Deadline) -> QueryResult: ...


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
        engine: Backend,
        names: tuple[str, ...],
        paths: tuple[Path, ...],
        prefixes: dict[str, str],
        etag: bytes,
    ) -> None:
        self.backend = backend
        self.engine = engine
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
        files = [KBFile.open(Path(item)) for item in paths]
        if index_dir is not None:
            return cls._open_index(files, Path(index_dir))
        engine: Backend
        if backend == "oxigraph":
            engine = OxigraphBackend()
        else:
            # Imported only when chosen: rdflib's SPARQL engine and pyparsing
            # cost every process that loads a KB several MB.
            from .rdflib_backend import RdflibBackend

            engine = RdflibBackend()
        # Parsing is nearly all of a big KB's load time: the files are parsed
        # one after another on a worker thread (GIL released) while this
        # thread hashes them for the ETag.
        digest = hashlib.blake2b(digest_size=8)
        digest.update(backend.encode() + b"\0")
        stop = threading.Event()

        def load_in_order(batch: list[KBFile]) -> None:
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
    def _open_index(cls, files: list[KBFile], index_dir: Path) -> KnowledgeBase:
        # An index returns unordered results in its own key order, not in
        # the in-memory store's insertion order: its answers get other ETags.
        digest = hashlib.blake2b(digest_size=8)
        digest.update(f"oxigraph-index {ox.__version__}\0".encode())
        for f in files:
            f.hash_into(digest)
        etag = digest.digest()
        engine = open_or_build_index(index_dir / f"{etag.hex()}.oxigraph", files)
        return cls._assemble("oxigraph", engine, files, etag)

    @classmethod
    def _assemble(cls, backend: str, engine: Backend, files: list[KBFile], etag: bytes) -> KnowledgeBase:
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
        return self.query_with(self.engine, sparql, row_limit=row_limit, time_budget_s=time_budget_s)

    @staticmethod
    def query_with(
        engine: Backend, sparql: str, *, row_limit: int = 1000, time_budget_s: float | None = None
    ) -> QueryResult:
        """:meth:`query` on another graph of the same kind (a written module's view)."""
        if row_limit < 0:
            raise ValueError(f"row_limit must be >= 0, got {row_limit}")
        if time_budget_s is not None and time_budget_s < 0:
            raise ValueError(f"time_budget_s must be >= 0, got {time_budget_s}")
        feature = refused_feature(sparql)
        if feature is not None:
            raise FeatureRefused(feature)
        return engine.query(sparql, row_limit, Deadline(time_budget_s))


def named_rows(kb: KnowledgeBase, name: str, params: Mapping[str, str] | None = None) -> list[dict[str, Term]]:
    """The rows of the named SELECT query ``name`` (:data:`~.named_queries.NAMED_QUERIES`)
    on ``kb``, as :meth:`~.results.SelectResult.as_dicts` gives them.

    Raises what :meth:`KnowledgeBase.query` raises, and
    :class:`~.errors.UnexpectedResult` if the query is not a SELECT."""
    return expect_select(kb.query(NAMED_QUERIES[name].render(params or {})), name).as_dicts()
