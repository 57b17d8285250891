"""Ask a robot's knowledge base: SPARQL text or a named query, decoded results."""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import secrets
from collections import OrderedDict
from collections.abc import AsyncGenerator, Callable, Mapping, Sequence
from dataclasses import dataclass

from ..clock import monotonic as loop_clock
from ..errors import CoapkbError
from ..model.results import QueryResult
from ..transport.base import ClientTransport, Endpoint, TransportError
from ..transport.messages import ContentFormat, Method, Request, Response, Status
from ..transport.observation import Notice, observe_fresh
from ..wire import codec
from .named_updates import NamedUpdate, encode_named_updates
from .write_concern import ACK_PARAM, Ack, decode_changed, parse_answer
from .write_ids import WID_PARAM, writer_name

#: CoAP's default Max-Age when a response carries none (RFC 7252 section 5.10.5).
DEFAULT_MAX_AGE_S = 60
#: Named-query answers a client keeps, the least recently used dropped first:
#: their keys carry the query's parameters (object names, positions), which
#: over a shift take as many values as the warehouse has products.
CACHE_ENTRIES = 512


@dataclass
class _Cached:
    expires: float
    etag: bytes | None
    result: QueryResult


@dataclass
class CacheStats:
    hits: int = 0
    revalidated: int = 0
    misses: int = 0


class QueryFailed(CoapkbError):
    """The robot answered with an error (4.xx/5.xx); ``str()`` is its diagnostic."""

    def __init__(self, response: Response) -> None:
        self.response = response
        super().__init__(f"{response.status.dotted} {response.status.name}: {response.text()}")


class WriteShort(QueryFailed):
    """5.04: the robot made the write (it is not undone and spreads on its
    own), but fewer holders confirmed it than the write concern asked.
    Sending it again would write it again."""

    def __init__(self, response: Response, reached: Ack, asked: Ack, version: bytes | None) -> None:
        super().__init__(response)
        self.reached = reached
        self.asked = asked
        #: The KB's version after the write (None if the robot did not say).
        self.version = version


@dataclass(frozen=True)
class WriteAnswer:
    """A write's 2.04."""

    #: The KB's new version (its ETag).
    version: bytes
    #: The level the write reached (None: the robot does not say, one
    #: older than write concerns).
    reached: Ack | None
    #: The robot's line: ``removed N, added M; ack LEVEL (...)``.
    text: str


class KBClient:
    """Queries over any :class:`ClientTransport`.

    With ``cache=True``, named-query answers are kept for their Max-Age (a
    robot's KB is read-only) and revalidated with their ETag afterwards (2.03
    Valid costs a few bytes instead of the answer): RFC 7252 section 5.6.

    Every write carries an id (``?wid=WRITER.N``, :mod:`.write_ids`), the
    same for each of its tries, so the robot makes it once: ``writer``
    names this client in it (None: a random name, a client of its own)."""

    def __init__(
        self,
        transport: ClientTransport,
        *,
        timeout: float = 30.0,
        cache: bool = False,
        cache_entries: int = CACHE_ENTRIES,
        clock: Callable[[], float] = loop_clock,
        writer: str | None = None,
    ) -> None:
        self.transport = transport
        #: The writer part of this client's write ids: unique to it, and to
        #: this run of it (a robot's includes its boot).
        self.writer = writer_name(writer) if writer else secrets.token_hex(4)
        self._writes = itertools.count(1)
        self.timeout = timeout
        #: The most answers the cache keeps (the least recently used go first).
        self.cache_entries = cache_entries
        self._cache: OrderedDict[tuple[object, ...], _Cached] | None = OrderedDict() if cache else None
        self._clock = clock
        self.cache_stats = CacheStats()

    def new_write_id(self) -> str:
        """An id for the next write, which each of its tries then carries."""
        return f"{self.writer}.{next(self._writes)}"

    async def sparql(
        self,
        peer: Endpoint,
        query: str,
        *,
        accept: ContentFormat = ContentFormat.CBOR,
        method: Method = Method.FETCH,
        timeout: float | None = None,
    ) -> QueryResult:
        """Run SPARQL text on ``peer`` (FETCH by default, RFC 8132)."""
        return decode(await self.call(peer, sparql_request(query, accept=accept, method=method), timeout))

    async def named(
        self,
        peer: Endpoint,
        name: str,
        params: Mapping[str, str] | None = None,
        *,
        accept: ContentFormat = ContentFormat.CBOR,
        timeout: float | None = None,
    ) -> QueryResult:
        """Run the named query ``/kb/q/<name>?params`` on ``peer``: a few bytes on the wire."""
        request = named_request(name, params, accept=accept)
        if self._cache is None:
            return decode(await self.call(peer, request, timeout))
        key = _cache_key(peer, request)
        cached = self._cache.get(key)
        if cached is not None:
            self._cache.move_to_end(key)
        now = self._clock()
        if cached is not None and now < cached.expires:
            self.cache_stats.hits += 1
            return cached.result
        if cached is not None and cached.etag is not None:
            request = dataclasses.replace(request, etags=(cached.etag,))
        response = await self.call(peer, request, timeout)
        max_age = DEFAULT_MAX_AGE_S if response.max_age is None else response.max_age
        if response.status == Status.VALID and cached is not None:
            self.cache_stats.revalidated += 1
            cached.expires = now + max_age
            return cached.result
        self.cache_stats.misses += 1
        result = decode(response)
        if max_age > 0:
            self._keep(key, _Cached(now + max_age, response.etag, result))
        return result

    def prime(self, peer: Endpoint, request: Request, max_age: int | None, payload: bytes) -> bool:
        """Keep ``payload``, a compact CBOR answer ``peer`` pushed before it
        was asked (coapkb.agent.fact_push), as if it had just answered
        ``request`` with it: :meth:`named` then takes it from the cache.
        False if there is no cache, it expires at once, or it does not decode."""
        max_age = DEFAULT_MAX_AGE_S if max_age is None else max_age
        if self._cache is None or max_age <= 0:
            return False
        try:
            result = codec.decode_cbor(payload)
        except codec.CodecError:
            return False
        self._keep(_cache_key(peer, request), _Cached(self._clock() + max_age, None, result))
        return True

    def fresh(self, peer: Endpoint, request: Request) -> bool:
        """Would :meth:`named` answer ``request`` to ``peer`` from the cache now?"""
        cached = None if self._cache is None else self._cache.get(_cache_key(peer, request))
        return cached is not None and self._clock() < cached.expires

    def _keep(self, key: tuple[object, ...], entry: _Cached) -> None:
        assert self._cache is not None
        self._cache[key] = entry
        self._cache.move_to_end(key)
        if len(self._cache) > self.cache_entries:
            self._cache.popitem(last=False)

    async def update(
        self,
        peer: Endpoint,
        update: str | bytes | Sequence[NamedUpdate],
        *,
        if_match: bytes | None = None,
        idempotent: bool = False,
        ack: Ack | None = None,
        timeout: float | None = None,
        write_id: str | None = None,
    ) -> bytes:
        """Write to ``peer``'s KB: SPARQL Update text, a compact patch
        (bytes, :func:`coapkb.kb.update.encode_patch`) or named updates
        (:mod:`coapkb.kb.named_updates`); PATCH, or iPATCH
        when ``idempotent``; ``ack`` the write concern (None: the robot's
        default, ``2``); ``write_id`` the write's id (None: a new one; a
        caller that sends a write again, to this robot or another holder,
        passes the id it sent it with, :meth:`new_write_id`).  Returns the
        KB's new version (its ETag); raises :class:`QueryFailed` with the
        robot's diagnostic, and :class:`WriteShort` (one) when the write
        was made but reached less than ``ack``."""
        return (await self.write(peer, update, if_match=if_match, idempotent=idempotent, ack=ack,
                                 timeout=timeout, write_id=write_id)).version

    async def write(
        self,
        peer: Endpoint,
        update: str | bytes | Sequence[NamedUpdate],
        *,
        if_match: bytes | None = None,
        idempotent: bool = False,
        ack: Ack | None = None,
        timeout: float | None = None,
        write_id: str | None = None,
    ) -> WriteAnswer:
        """:meth:`update`, answering the whole 2.04: the version, the level
        the write reached and the robot's line."""
        text = isinstance(update, str)
        if not isinstance(update, (str, bytes)):
            update = encode_named_updates(update)
        query = {} if ack is None else {ACK_PARAM: str(ack)}
        query[WID_PARAM] = write_id or self.new_write_id()
        request = Request(
            Method.IPATCH if idempotent else Method.PATCH,
            "/kb",
            query,
            payload=update.encode("utf-8") if isinstance(update, str) else update,
            content_format=ContentFormat.TEXT if text else ContentFormat.CBOR,
            # A machine's write (CBOR) takes its answer in CBOR too: a sixth of the text's bytes.
            accept=None if text else ContentFormat.CBOR,
            if_match=() if if_match is None else (if_match,),
        )
        try:
            response = await self.call(peer, request, timeout)
        except QueryFailed as exc:
            if exc.response.status == Status.GATEWAY_TIMEOUT:
                short = parse_answer(exc.response.text(), short=True)
                if short is not None and short.asked is not None:
                    raise WriteShort(exc.response, short.reached, short.asked, short.version) from None
            raise
        if response.content_format == ContentFormat.CBOR:
            try:
                removed, added, level = decode_changed(response.payload)
            except ValueError as exc:  # written all the same: the robot said 2.04
                return WriteAnswer(response.etag or b"", None, f"2.04 Changed ({exc})")
            return WriteAnswer(response.etag or b"", level, f"removed {removed}, added {added}; ack {level}")
        said = parse_answer(response.text(), short=False)
        return WriteAnswer(response.etag or b"", None if said is None else said.reached, response.text())

    async def call(self, peer: Endpoint, request: Request, timeout: float | None = None) -> Response:
        response = await self.transport.request(peer, request, timeout=timeout or self.timeout)
        if not response.status.is_success:
            raise QueryFailed(response)
        return response

    async def observe(
        self,
        peer: Endpoint,
        request: Request,
        *,
        on_notice: Callable[[Notice], None] | None = None,
    ) -> AsyncGenerator[QueryResult, None]:
        """The answer to ``request`` (:func:`sparql_request` by FETCH, or
        :func:`named_request`), then again each time it changes (RFC 7641).

        The observation notices when the robot lost it: after the answer's
        Max-Age (2 s on a writable KB) and a margin with no notification, it
        registers again, and keeps trying while the robot does not answer
        (:func:`~coapkb.transport.observation.observe_fresh`); each time it
        does, ``on_notice`` is told, and the answer is yielded if it changed
        meanwhile.  An error answer raises :class:`QueryFailed` (it ends the
        observation); the first registration's :class:`TransportError` is raised."""
        async with contextlib.aclosing(observe_fresh(self.transport, peer, request, on_notice=on_notice)) as answers:
            async for response in answers:
                if not response.status.is_success:
                    raise QueryFailed(response)
                yield decode(response)


def sparql_request(query: str, *, accept: ContentFormat = ContentFormat.CBOR, method: Method = Method.FETCH) -> Request:
    """SPARQL text for ``/kb/sparql``: its body by FETCH or POST, ``?q=`` by GET."""
    if method == Method.GET:
        return Request(Method.GET, "/kb/sparql", {"q": query}, accept=accept)
    return Request(method, "/kb/sparql", payload=query.encode("utf-8"), content_format=ContentFormat.TEXT,
                   accept=accept)


def named_request(name: str, params: Mapping[str, str] | None = None, *,
                  accept: ContentFormat = ContentFormat.CBOR) -> Request:
    """The named query ``/kb/q/<name>?params``."""
    return Request(Method.GET, f"/kb/q/{name}", dict(params or {}), accept=accept)


def _cache_key(peer: Endpoint, request: Request) -> tuple[object, ...]:
    return (peer, request.path, tuple(sorted(request.query.items())), request.accept)


def decode(response: Response) -> QueryResult:
    """Decode a successful query response by its content-format."""
    if response.content_format == ContentFormat.CBOR:
        return codec.decode_cbor(response.payload)
    if response.content_format == ContentFormat.JSON:
        return codec.decode_json(response.payload)
    raise TransportError(f"unexpected content-format {response.content_format} in a query answer")
