"""The knowledge base's resources: ``/kb``, ``/kb/sparql``, ``/kb/q/<name>`` and ``/kb/dump``.

Transport-neutral handlers mounted on a :class:`~coapkb.transport.router.Router`; every
transport exposes them unchanged.  A writable KB (:class:`~.live.LiveKB`) also takes
PATCH and iPATCH on ``/kb`` (RFC 8132), and its queries are observable (RFC 7641; a
FETCH's body is part of what is observed, RFC 8132 section 2.4).
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import math
import threading
import time
from typing import TYPE_CHECKING

import cbor2

from ..model.results import QueryResult
from ..transport.base import ResourceInfo
from ..transport.messages import ContentFormat, Method, Request, Response, Status
from ..transport.router import Router
from ..wire import codec
from .answer_cache import AnswerCache
from .dump_resource import DumpResource
from .errors import KBError, QueryRefused, QuerySyntaxError, QueryTimeout, UpdateRefused
from .limits import QueryLimits
from .live import LiveKB
from .named_queries import NamedQuery, named_queries_for
from .store import QueryableKB
from .write_resource import WriteResource, caught_up

if TYPE_CHECKING:
    from .replication import Replicator

RESULT_FORMATS = (ContentFormat.CBOR, ContentFormat.JSON)


def negotiate(accept: int | None) -> ContentFormat | None:
    """The result format for an Accept option; CBOR when none is given."""
    if accept is None:
        return ContentFormat.CBOR
    return ContentFormat(accept) if accept in RESULT_FORMATS else None


def encode_result(result: QueryResult, fmt: ContentFormat) -> bytes:
    return codec.encode_cbor(result) if fmt == ContentFormat.CBOR else codec.encode_json(result)


#: What a write to a read-only KB is answered with (4.05), besides the status:
#: a robot's or a server's owner learns how to make it writable.
READ_ONLY = ("this knowledge base is read-only: a robot takes writes unless its TOML says kb_writable = false "
             "(coapkb team: unless --read-only); coapkb serve takes them with --writable or --credentials")


class KBResources:
    """Answers SPARQL over one knowledge base, and takes writes if it is a
    :class:`~.live.LiveKB` (``replicator`` then spreads them)."""

    def __init__(
        self,
        kb: QueryableKB,
        limits: QueryLimits | None = None,
        *,
        threads: bool = True,
        replicator: Replicator | None = None,
        read_only: str = READ_ONLY,
    ) -> None:
        self.kb = kb
        self.live = kb if isinstance(kb, LiveKB) else None
        #: The diagnostic of a write refused (4.05): why, and how to make it writable.
        self.read_only = read_only
        self.replicator = replicator
        self.limits = limits or QueryLimits()
        #: False: every query runs on the event loop (the simulator's
        #: processes share one thread, and a thread's timing is not replayable).
        self.threads = threads
        self.named = {q.name: q for q in named_queries_for(kb.names)}
        self.running = 0
        self.answers = AnswerCache()
        #: named query -> the longest any of its runs took (s); runs inline once known cheap.
        self.slowest_run: dict[str, float] = {}
        #: ``/kb/dump``.
        self.dumps = DumpResource(kb, self.limits.retry_after_s, self.max_age_s, threads=threads)
        #: PATCH and iPATCH of ``/kb``, on a writable KB.
        self.writes = None if self.live is None else WriteResource(self.live, self.limits, replicator)

    @property
    def max_age_s(self) -> int:
        return self.limits.max_age_s if self.live is None else self.limits.live_max_age_s

    def mount(self, router: Router) -> None:
        live = self.live is not None
        router.add(
            ResourceInfo("/kb", rt="coapkb.kb", ct=RESULT_FORMATS, obs=live, quiet=live,
                         title="knowledge base summary" + ("; PATCH/iPATCH a SPARQL Update to write" if live else ""),
                         # PATCH on a read-only KB too: answered 4.05 with how to make it writable.
                         methods=("GET", "PATCH", "iPATCH")),
            self.kb_resource,
        )
        router.add(
            ResourceInfo(
                "/kb/sparql",
                rt="sparql",
                ct=RESULT_FORMATS,
                obs=live, quiet=live,
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
                    obs=live, quiet=live,
                    title=_link_title(query),
                ),
                self.named_query,
            )
        router.add(
            ResourceInfo("/kb/dump", rt="coapkb.dump", ct=(ContentFormat.TEXT,),
                         title="every triple, N-Triples, sorted (?module=NAME: one module's)"),
            self.dumps.dump,
        )
        if self.live is not None:
            self.live.listeners.append(lambda modules: self._changed(router, modules))
        if self.replicator is not None:
            self.replicator.mount(router)

    def _changed(self, router: Router, modules: frozenset[str]) -> None:
        """Tell the observers of what a change may have changed: an
        unchanged answer is not sent again (the transports compare)."""
        router.notify("/kb")
        router.notify("/kb/sparql")
        for query in self.named.values():
            if query.kb is None or query.kb in modules:
                router.notify(f"/kb/q/{query.name}")

    async def kb_resource(self, request: Request) -> Response:
        if request.method in (Method.PATCH, Method.IPATCH):
            return await self.write(request)
        return await self.get_info(request)

    async def write(self, request: Request) -> Response:
        """PATCH/iPATCH ``/kb`` (:class:`~.write_resource.WriteResource`)."""
        if self.writes is None:
            return Response.error(Status.METHOD_NOT_ALLOWED, self.read_only)
        return await self.writes.write(request)

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
        if self.live is not None:
            info["versions"] = {m: self.live.module_version(m).hex() for m in self.live.names}
        payload = cbor2.dumps(info) if fmt == ContentFormat.CBOR else json.dumps(info).encode()
        return Response(Status.CONTENT, payload, fmt, max_age=self.max_age_s, etag=self.kb.etag)

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
        await caught_up(self.replicator)
        return await self.answer(text, request.accept, request.etags)

    async def named_query(self, request: Request) -> Response:
        # Mounted once per named query: an unknown name is the router's 4.04,
        # which lists the names there are.
        name = request.path.rsplit("/", 1)[1]
        query = self.named[name]
        params = dict(request.query)
        at = params.pop("at", None)
        try:
            text = query.render(params)
            task = _task_number(at)
        except ValueError as exc:
            return Response.error(Status.BAD_REQUEST, str(exc))
        await caught_up(self.replicator)
        if task is not None and self.live is not None:
            return self._pinned(text, task, request.accept)
        return await self.answer(text, request.accept, request.etags, shape=name)

    def _pinned(self, text: str, task: int, accept: int | None) -> Response:
        """``?at=TASK``: the answer as first given for that task (LiveKB.query_at),
        so every robot deciding the task reads the same knowledge.  A named
        query is small: it runs inline, outside the answer cache."""
        assert self.live is not None
        fmt = negotiate(accept)
        if fmt is None:
            return _not_acceptable(accept)
        try:
            result = self.live.query_at(task, text)
        except KBError as exc:
            return Response.error(Status.BAD_REQUEST, str(exc))
        payload = encode_result(result, fmt)
        etag = hashlib.blake2s(payload, digest_size=8).digest()
        return Response(Status.CONTENT, payload, fmt, max_age=self.max_age_s, etag=etag)

    async def answer(
        self, text: str, accept: int | None, etags: tuple[bytes, ...] = (), *, shape: str | None = None
    ) -> Response:
        """Run a query within the limits and encode it in the negotiated format.

        An answer's ETag follows from the KB's version (its ETag), the
        format and the query text: a client that still holds it gets 2.03
        Valid and the query is not even run.  ``shape`` names the
        query's kind (a named query's name) for the inline fast path; free
        SPARQL text has none and always runs on a thread."""
        fmt = negotiate(accept)
        if fmt is None:
            return _not_acceptable(accept)
        etag = hashlib.blake2s(self.kb.etag + fmt.to_bytes(2, "big") + text.encode(), digest_size=8).digest()
        if etag in etags:
            return Response(Status.VALID, max_age=self.max_age_s, etag=etag)
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
                async with asyncio.timeout(limits.time_budget_s + 0.5):
                    result = await self._evaluate(text, shape)
        except QuerySyntaxError as exc:
            return Response.error(Status.BAD_REQUEST, f"malformed SPARQL: {exc}")
        except UpdateRefused as exc:
            if self.live is not None:  # a writable KB takes it elsewhere
                return Response.error(Status.FORBIDDEN, f"refused: {', '.join(exc.operations)} is SPARQL Update, "
                                      "not a query: send it by PATCH to /kb (coapkb update)")
            return Response.error(Status.FORBIDDEN, f"refused: {exc}")
        except QueryRefused as exc:  # SERVICE/FROM that would fetch from the network
            return Response.error(Status.FORBIDDEN, f"refused: {exc}")
        except (TimeoutError, QueryTimeout):
            return Response.error(
                Status.SERVICE_UNAVAILABLE,
                f"query exceeded the {limits.time_budget_s}s time budget",
                max_age=limits.retry_after_s,
            )
        except KBError as exc:
            return Response.error(Status.BAD_REQUEST, str(exc))
        payload = encode_result(result, fmt)
        return Response(Status.CONTENT, payload, fmt, max_age=self.max_age_s, etag=etag)


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
            except BaseException as exc:  # noqa: BLE001 - delivered to the awaiting request
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


def _task_number(at: str | None) -> int | None:
    if at is None:
        return None
    if not at.isdigit() or len(at) > 12:
        raise ValueError(f"at= takes a task number, not {at!r}")
    return int(at)


def _not_acceptable(accept: int | None) -> Response:
    offered = " or ".join(f"{int(f)} ({f.name.lower()})" for f in RESULT_FORMATS)
    return Response.error(Status.NOT_ACCEPTABLE, f"cannot answer in content-format {accept}; use {offered}")


def _link_title(query: NamedQuery) -> str:
    params = "&".join(f"{p}=..." for p in query.params)
    return f"{query.description} ?{params}" if params else query.description
