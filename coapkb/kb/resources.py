"""The knowledge base's resources: ``/kb``, ``/kb/sparql`` and ``/kb/q/<name>``.

Transport-neutral handlers mounted on a :class:`~coapkb.transport.router.Router`; the
CoAP and ZeroMQ transports expose them unchanged.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import math
import threading
import time
from dataclasses import dataclass

import cbor2

from ..wire import codec
from .errors import KBError, QueryRefused, QuerySyntaxError, QueryTimeout
from .store import KnowledgeBase
from ..transport.messages import ContentFormat, Method, Request, Response, Status
from .answer_cache import AnswerCache
from .named_queries import NamedQuery, named_queries_for
from .results import QueryResult
from ..transport.router import Router
from ..transport.base import ResourceInfo

RESULT_FORMATS = (ContentFormat.CBOR, ContentFormat.JSON)


@dataclass(frozen=True)
class QueryLimits:
    """Per-query limits a robot enforces so one request cannot starve the rest."""

    row_limit: int = 1000
    time_budget_s: float = 2.0
    max_request_bytes: int = 8192
    #: Max-Age of query answers: the KB is read-only, so answers stay fresh.
    max_age_s: int = 300
    #: Max-Age on a 5.03 when the time budget ran out: when to try again.
    retry_after_s: int = 5
    #: Queries evaluated at once (including ones still running past their
    #: budget); beyond this the robot answers 5.03 at once.
    max_concurrent: int = 8
    #: A named query whose every run so far took less than this runs inline
    #: on the event loop: starting a thread costs more than the query (an
    #: index lookup on pyoxigraph takes tens of microseconds).  0 disables.
    inline_below_s: float = 0.002

    def __post_init__(self) -> None:
        for name in ("row_limit", "max_request_bytes", "max_age_s", "retry_after_s", "max_concurrent"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if not self.time_budget_s > 0:
            raise ValueError(f"time_budget_s must be positive, got {self.time_budget_s}")
        if not 0 <= self.inline_below_s < self.time_budget_s:
            raise ValueError(f"inline_below_s must be in [0, time_budget_s), got {self.inline_below_s}")


def negotiate(accept: int | None) -> ContentFormat | None:
    """The result format for an Accept option; CBOR when none is given."""
    if accept is None:
        return ContentFormat.CBOR
    return ContentFormat(accept) if accept in RESULT_FORMATS else None


def encode_result(result: QueryResult, fmt: ContentFormat) -> bytes:
    return codec.encode_cbor(result) if fmt == ContentFormat.CBOR else codec.encode_json(result)


class KBResources:
    """Answers SPARQL over one (read-only) knowledge base."""

    def __init__(self, kb: KnowledgeBase, limits: QueryLimits | None = None, *, threads: bool = True) -> None:
        self.kb = kb
        self.limits = limits or QueryLimits()
        #: False: every query runs on the event loop (the simulator's
        #: processes share one thread, and a thread's timing is not replayable).
        self.threads = threads
        self.named = {q.name: q for q in named_queries_for(kb.names)}
        self.running = 0
        self.answers = AnswerCache()
        #: named query -> the longest any of its runs took (s); runs inline once known cheap.
        self.slowest_run: dict[str, float] = {}

    def mount(self, router: Router) -> None:
        router.add(
            ResourceInfo("/kb", rt="coapkb.kb", ct=RESULT_FORMATS, title="knowledge base summary"),
            self.get_info,
        )
        router.add(
            ResourceInfo(
                "/kb/sparql",
                rt="sparql",
                ct=RESULT_FORMATS,
                title="SPARQL 1.1 query (FETCH/POST body or GET ?q=)",
                methods=("GET", "POST", "FETCH"),
            ),
            self.sparql,
        )
        for query in self.named.values():
            router.add(
                ResourceInfo(
                    f"/kb/q/{query.name}",
                    rt="coapkb.q",
                    ct=RESULT_FORMATS,
                    title=_link_title(query),
                ),
                self.named_query,
            )

    async def get_info(self, request: Request) -> Response:
        fmt = negotiate(request.accept)
        if fmt is None:
            return _not_acceptable(request.accept)
        info = {
            "names": list(self.kb.names),
            "backend": self.kb.backend,
            "triples": self.kb.triple_count,
            "prefixes": dict(self.kb.prefixes),
            "queries": {q.name: list(q.params) for q in self.named.values()},
            "etag": self.kb.etag.hex(),
        }
        payload = cbor2.dumps(info) if fmt == ContentFormat.CBOR else json.dumps(info).encode()
        return Response(Status.CONTENT, payload, fmt, max_age=self.limits.max_age_s, etag=self.kb.etag)

    async def sparql(self, request: Request) -> Response:
        if request.method == Method.GET:
            if "q" not in request.query:
                return Response.error(Status.BAD_REQUEST, "GET needs the query in ?q= (or use FETCH/POST)")
            text = request.query["q"]
            size = len(text.encode("utf-8"))
        else:
            if request.content_format not in (None, ContentFormat.TEXT):
                return Response.error(
                    Status.UNSUPPORTED_CONTENT_FORMAT,
                    f"query body must be text/plain (content-format 0), got {request.content_format}",
                )
            size = len(request.payload)
            try:
                text = request.payload.decode("utf-8")
            except UnicodeDecodeError as exc:
                return Response.error(Status.BAD_REQUEST, f"query is not UTF-8: {exc}")
        if size > self.limits.max_request_bytes:
            return Response.error(
                Status.REQUEST_ENTITY_TOO_LARGE,
                f"query is {size} bytes; this robot accepts at most {self.limits.max_request_bytes}",
            )
        if not text.strip():
            return Response.error(Status.BAD_REQUEST, "empty query")
        return await self.answer(text, request.accept, request.etags)

    async def named_query(self, request: Request) -> Response:
        # Mounted once per named query: an unknown name is the router's 4.04,
        # which lists the names there are.
        name = request.path.rsplit("/", 1)[1]
        query = self.named[name]
        try:
            text = query.render(request.query)
        except ValueError as exc:
            return Response.error(Status.BAD_REQUEST, str(exc))
        return await self.answer(text, request.accept, request.etags, shape=name)

    async def answer(
        self, text: str, accept: int | None, etags: tuple[bytes, ...] = (), *, shape: str | None = None
    ) -> Response:
        """Run a query within the limits and encode it in the negotiated format.

        The KB is read-only, so an answer's ETag follows from the KB's ETag,
        the format and the query text: a client that still holds it gets
        2.03 Valid and the query is not even run.  ``shape`` names the
        query's kind (a named query's name) for the inline fast path; free
        SPARQL text has none and always runs on a thread."""
        fmt = negotiate(accept)
        if fmt is None:
            return _not_acceptable(accept)
        limits = self.limits
        etag = hashlib.blake2s(self.kb.etag + fmt.to_bytes(2, "big") + text.encode(), digest_size=8).digest()
        if etag in etags:
            return Response(Status.VALID, max_age=limits.max_age_s, etag=etag)
        return await self.answers.get_or_compute(etag, lambda: self._run(text, fmt, etag, shape))

    async def _run(self, text: str, fmt: ContentFormat, etag: bytes, shape: str | None) -> Response:
        limits = self.limits
        slowest = self.slowest_run.get(shape) if shape is not None else None
        inline = not self.threads or (slowest is not None and slowest < limits.inline_below_s)
        if not inline and self.running >= limits.max_concurrent:
            return Response.error(
                Status.SERVICE_UNAVAILABLE,
                f"{self.running} queries are running; try again later",
                max_age=limits.retry_after_s,
            )
        try:
            if inline:
                result = self._evaluate_inline(text, shape)
            else:
                result = await asyncio.wait_for(self._evaluate(text, shape), limits.time_budget_s + 0.5)
        except QuerySyntaxError as exc:
            return Response.error(Status.BAD_REQUEST, f"malformed SPARQL: {exc}")
        except QueryRefused as exc:  # SPARQL Update, or SERVICE/FROM that would fetch from the network
            return Response.error(Status.FORBIDDEN, f"refused: {exc}")
        except (QueryTimeout, asyncio.TimeoutError):
            return Response.error(
                Status.SERVICE_UNAVAILABLE,
                f"query exceeded the {limits.time_budget_s}s time budget",
                max_age=limits.retry_after_s,
            )
        except KBError as exc:
            return Response.error(Status.BAD_REQUEST, str(exc))
        payload = encode_result(result, fmt)
        return Response(Status.CONTENT, payload, fmt, max_age=limits.max_age_s, etag=etag)


    def _record_run(self, shape: str | None, seconds: float) -> None:
        if shape is not None:
            self.slowest_run[shape] = max(seconds, self.slowest_run.get(shape, 0.0))

    def _evaluate_inline(self, text: str, shape: str | None) -> QueryResult:
        """Run a query known to be cheap right here, on the event loop.

        The KB's deadline still applies between rows; a run that turns out
        slow (other parameters, a bigger answer) is recorded, and the
        query's next runs go to a thread again."""
        started = time.thread_time()
        try:
            result = self.kb.query(text, row_limit=self.limits.row_limit, time_budget_s=self.limits.time_budget_s)
        except QueryTimeout:
            self._record_run(shape, math.inf)  # a run that ran out of time is never cheap
            raise
        self._record_run(shape, time.thread_time() - started)
        return result

    def _evaluate(self, text: str, shape: str | None) -> asyncio.Future[QueryResult]:
        """Run the query on its own daemon thread, so the server keeps answering.

        The KB checks the time budget between result rows; a query whose cost
        lies in one step (a sort, an aggregate over a huge join) cannot be
        interrupted and keeps its thread until it ends.  A daemon thread never
        holds up the robot's shutdown, and ``running`` counts such queries
        until they really finish, so they cannot pile up unbounded."""
        loop = asyncio.get_running_loop()
        future: asyncio.Future[QueryResult] = loop.create_future()
        limits = self.limits

        def settle(outcome: QueryResult | BaseException, seconds: float) -> None:
            self.running -= 1
            # a run that ran out of time never makes the query look cheap
            self._record_run(shape, math.inf if isinstance(outcome, QueryTimeout) else seconds)
            if future.done():  # the caller already gave up (time budget)
                return
            if isinstance(outcome, BaseException):
                future.set_exception(outcome)
            else:
                future.set_result(outcome)

        def work() -> None:
            outcome: QueryResult | BaseException
            # CPU time of this thread: the query's own cost, not its waits for the GIL
            started = time.thread_time()
            try:
                outcome = self.kb.query(text, row_limit=limits.row_limit, time_budget_s=limits.time_budget_s)
            except BaseException as exc:  # delivered to the awaiting request
                outcome = _without_frames(exc) if isinstance(exc, KBError) else exc
            try:
                loop.call_soon_threadsafe(settle, outcome, time.thread_time() - started)
            except RuntimeError:  # the loop is closed: the robot has shut down
                pass

        self.running += 1
        threading.Thread(target=work, name="sparql-query", daemon=True).start()
        return future


def _without_frames(exc: BaseException) -> BaseException:
    """``exc`` and the exceptions it chains, without their tracebacks.

    Their frames hold the backend's result iterator, and pyoxigraph's may
    only be dropped on the thread that made it (pyo3 "unsendable"): dropped
    with the exception on the event loop, it is leaked with an error
    printed, once for every query that failed or ran out of time.  A
    KBError is the query's fault, so its traceback tells nobody anything."""
    seen: set[int] = set()
    pending: list[BaseException | None] = [exc]
    while pending:
        current = pending.pop()
        if current is None or id(current) in seen:
            continue
        seen.add(id(current))
        current.__traceback__ = None
        pending += [current.__cause__, current.__context__]
    return exc


def _not_acceptable(accept: int | None) -> Response:
    offered = " or ".join(f"{int(f)} ({f.name.lower()})" for f in RESULT_FORMATS)
    return Response.error(Status.NOT_ACCEPTABLE, f"cannot answer in content-format {accept}; use {offered}")


def _link_title(query: NamedQuery) -> str:
    params = "&".join(f"{p}=..." for p in query.params)
    return f"{query.description} ?{params}" if params else query.description
