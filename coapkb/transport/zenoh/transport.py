"""Zenoh transport: a robot's resources as a Zenoh queryable, behind coapkb's interface.

:class:`ZenohServerTransport` opens a session in peer mode listening on its
endpoint and declares one queryable, ``coapkb/**``.
:class:`ZenohClientTransport` opens one client-mode session per peer, lazily,
scouting off; when a query finds no route it closes that session and tries
once more on a fresh one (:meth:`ZenohClientTransport._exchange`).  How
messages map onto Zenoh's queries, replies and samples, and which locator a
scheme becomes, is :mod:`.mapping`; mutual TLS is :mod:`.security`, a QUIC
link without the team's keys :mod:`.anonymous_tls`.

Zenoh calls back from its own threads: every callback only copies what it
got into Python values and hands them to the event loop
(``call_soon_threadsafe``).  Sessions open and close on a small executor
whose threads start from the loop's thread, so a link's socket lives in the
loop thread's network namespace.

docs/zenoh.md specifies the rest, with the reasons: the mapping and Observe,
errors (:class:`PeerUnreachable`), the link protocols, security and what the
traffic counters hold.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import os
import socket
import threading
import time
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import zenoh

from ..base import (
    Endpoint,
    PeerTimeout,
    PeerUnreachable,
    Service,
    TransportError,
    free_port,
)
from ..core import ClientCore, CoreOptions, ServerCore, check_scheme, post
from ..messages import Method, Request, Response, Status
from ..observation import Delivery, ObserverState, put_latest
from . import anonymous_tls
from .mapping import (
    KEY_ROOT,
    LINK_PROTOCOLS,
    NOTIFY_ROOT,
    MappingError,
    Observe,
    RequestHeader,
    ResponseHeader,
    encode_request_header,
    encode_response_header,
    encoding_for,
    key_for_path,
    link_for,
    locator,
    parameters_text,
    request_from_query,
    response_from_reply,
)
from .security import ZenohClientSecurity, ZenohServerSecurity

__all__ = ["ZenohClientTransport", "ZenohOptions", "ZenohServerTransport", "session_config"]

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class ZenohOptions(CoreOptions):
    """Limits shared by client and server.  Observations are not told apart
    by client: ``max_observations`` holds for the server."""

    #: Client: how long one attempt to open a session may take (Zenoh's
    #: ``transport/unicast/open_timeout``); None: Zenoh's own, 10 s.  A dead
    #: peer refuses a TCP connection at once, but a QUIC (or reliable-UDP)
    #: handshake with it fails only at this timeout.
    open_timeout_s: float | None = None


def session_config(mode: str, *, listen: tuple[str, ...] = (), connect: tuple[str, ...] = ()) -> zenoh.Config:
    """A session on explicit endpoints only: no multicast or gossip scouting."""
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("scouting/gossip/enabled", "false")
    config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return config


def _secured_locator(endpoint: Endpoint, security: ZenohClientSecurity | ZenohServerSecurity | None) -> str:
    """The endpoint's locator; the secured link's (``tls/`` for ``tcp/``, ``quic/`` as it is) with security."""
    if security is None:
        return locator(endpoint)
    return security.locator(locator(endpoint))


def _canonical(key: str, path: str) -> bool:
    try:
        return key_for_path(path) == key
    except ValueError:
        return False


def _bytes(z: zenoh.ZBytes | None) -> bytes | None:
    return None if z is None else z.to_bytes()


def _close(session: zenoh.Session) -> None:
    """Close ``session`` (blocking: not on the loop).  A client session whose
    peer has gone waits for its reconnect attempt; over QUIC links
    (``zenoh+quic``, ``zenoh+udp``) that lasts the open timeout (10 s) and
    Zenoh may report "close operation timed out": the session is gone all the same."""
    try:
        session.close()
    except zenoh.ZError as exc:
        log.debug("closing a zenoh session: %s", str(exc).split(" at ", 1)[0])


def _resolve(future: asyncio.Future[None]) -> None:
    if not future.done():  # cancelled by a waiter's timeout
        future.set_result(None)


def _close_in_thread(session: zenoh.Session) -> asyncio.Future[None]:
    """Close a client session on a daemon thread of its own; the future is
    done when it is closed.  A client session that lost its peer is retrying
    the connection, and its close waits for that attempt: at once over TCP
    (refused), but over QUIC only at the open timeout (10 s), which would hold
    up an executor thread, and a process's exit (it joins executor threads,
    not daemon ones)."""
    loop = asyncio.get_running_loop()
    closed: asyncio.Future[None] = loop.create_future()

    def run() -> None:
        _close(session)
        post(loop, _resolve, closed)

    threading.Thread(target=run, name="zenoh close", daemon=True).start()
    return closed


# =========================================================================== server


def _finish(query: zenoh.Query) -> None:
    """End ``query`` for the querier now (Zenoh sends its final message when
    the query is dropped, which Python's finaliser does not promise to do soon)."""
    with contextlib.suppress(zenoh.ZError):
        query.drop()


@dataclass(frozen=True)
class _Incoming:
    """What a query carried, copied out of Zenoh's objects on its thread."""

    key: str
    parameters: str
    payload: bytes
    encoding: str | None
    attachment: bytes | None
    #: The querier's session id as it declared it (``source_info``), or None.
    source: str | None = None

    @property
    def size(self) -> int:
        selector = len(self.key) + (1 + len(self.parameters) if self.parameters else 0)  # key?parameters
        return selector + len(self.payload) + len(self.attachment or b"")


class ZenohServerTransport(ServerCore):
    """Serves a :class:`Service` as the queryable ``coapkb/**`` of a peer-mode session.

    Create with :meth:`start`.  Requests are handled concurrently (at most
    ``options.max_concurrent_requests`` at once).  Queries that are not a
    coapkb request are counted in :attr:`malformed` and get an error reply.
    """

    def __init__(
        self,
        service: Service,
        endpoint: Endpoint,
        session: zenoh.Session,
        executor: ThreadPoolExecutor,
        options: ZenohOptions,
        security: ZenohServerSecurity | None = None,
    ) -> None:
        """Private: use :meth:`start`, which opens the session first."""
        super().__init__(service, endpoint, options, log, "zenoh server")
        #: Authenticates clients (mTLS), or None.
        self._security = security
        self._session = session
        self._executor = executor
        self._loop = asyncio.get_running_loop()
        self._queryable = session.declare_queryable(f"{KEY_ROOT}/**", zenoh.handlers.Callback(self._on_query))

    @classmethod
    async def start(
        cls, service: Service, endpoint: Endpoint, *, options: ZenohOptions | None = None,
        security: ZenohServerSecurity | None = None,
    ) -> ZenohServerTransport:
        """Listen on ``endpoint`` and start serving.

        Port 0 picks a free port; the returned transport's :attr:`endpoint`
        has it.  Raises :class:`TransportError` if Zenoh cannot listen there
        (port in use, no such address).  ``security``: mTLS
        (:mod:`coapkb.security.zenoh_tls`), or None."""
        check_scheme(endpoint, *LINK_PROTOCOLS)
        _secured_locator(endpoint, security)  # zenoh+udp with security: refused before a port is taken
        if endpoint.port == 0:
            kind = socket.SOCK_DGRAM if link_for(endpoint).datagram else socket.SOCK_STREAM
            endpoint = Endpoint(endpoint.scheme, endpoint.host, free_port(endpoint.host, kind))
        executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"zenoh server {endpoint}")
        config = session_config("peer", listen=(_secured_locator(endpoint, security),))
        if security is not None:
            security.configure(config)
        elif link_for(endpoint).needs_tls:  # QUIC will not listen without a certificate
            anonymous_tls.configure_listener(config)
        try:
            session = await asyncio.get_running_loop().run_in_executor(executor, zenoh.open, config)
        except zenoh.ZError as exc:
            executor.shutdown(wait=False)
            raise TransportError(f"cannot listen on {endpoint}: {exc}") from None
        return cls(service, endpoint, session, executor, options or ZenohOptions(), security)

    def _stop_receiving(self) -> None:
        with contextlib.suppress(zenoh.ZError):
            self._queryable.undeclare()

    async def _close_transport(self) -> None:
        await self._loop.run_in_executor(self._executor, _close, self._session)
        self._executor.shutdown(wait=False)

    # ------------------------------------------------------------------ receiving

    def _on_query(self, query: zenoh.Query) -> None:
        """On a Zenoh thread: copy the query out and hand it to the loop."""
        encoding = query.encoding
        source = query.source_info if self._security is not None else None
        incoming = _Incoming(
            str(query.key_expr),
            str(query.parameters),
            _bytes(query.payload) or b"",
            None if encoding is None else str(encoding),
            _bytes(query.attachment),
            None if source is None else str(source.source_id.zid),
        )
        post(self._loop, self._accept, query, incoming)

    def _accept(self, query: zenoh.Query, incoming: _Incoming) -> None:
        if self._closed:
            return
        self._count_received(incoming.size)
        try:
            request, header = request_from_query(
                incoming.key, incoming.parameters, incoming.payload, incoming.encoding, incoming.attachment
            )
        except MappingError as exc:
            self._malformed(f"a query on {incoming.key[:80]!r}", str(exc))
            self._reply_error(query, f"4.00 not a coapkb request: {exc}")
            _finish(query)
            return
        sender = None
        if self._security is not None:
            if not _canonical(incoming.key, request.path):
                # Zenoh's access control matches key expressions: a wildcard or a
                # re-encoded segment would reach /tasks past it.
                self._reply_error(query, "4.00 not the canonical key of its path")  # no key to reply on
                _finish(query)
                return
            sender = self._security.sender(self._session, incoming.source)
        if header.observe is Observe.DEREGISTER:
            # A deregistration only ends an observation: any member may send one.
            refused = self._refusal(sender, Method.GET, request.path)
            if refused is None:
                self._observations.deregister(None, header.notify_key or "")
            self._reply(query, refused or Response(Status.DELETED))
            _finish(query)
            return
        self._spawn(self._serve(query, request, header, sender))

    # ------------------------------------------------------------------ answering

    async def _serve(self, query: zenoh.Query, request: Request, header: RequestHeader, sender: str | None) -> None:
        async def answer(response: Response, seq: int | None) -> bool:
            # The first answer rides on the query, not on the observer's key: whether
            # notifications reach the observer is for the publisher's matching status to tell.
            self._reply(query, response, seq)
            return True

        notify_key = header.notify_key
        try:
            async with self._slots:
                await self._answer(
                    request, answer, sender=sender,
                    observe=(None, notify_key) if header.observe is Observe.REGISTER and notify_key else None,
                    notifier=lambda gone: self._publication(notify_key or "", gone),
                )
        finally:
            _finish(query)

    @staticmethod
    def _header(response: Response, seq: int | None = None) -> bytes | None:
        return encode_response_header(ResponseHeader(response.status, response.max_age, response.etag, seq))

    def _reply(self, query: zenoh.Query, response: Response, seq: int | None = None) -> None:
        """Answer on the query's own key (it is concrete: clients send no wildcards)."""
        attachment = self._header(response, seq)
        key = query.key_expr
        try:
            query.reply(key, response.payload, encoding=encoding_for(response.content_format), attachment=attachment)
        except zenoh.ZError as exc:  # the session is closing, or the querier's key is odd
            log.debug("zenoh server %s: reply failed: %s", self.endpoint, exc)
            return
        self._count_sent(len(str(key)) + len(response.payload) + len(attachment or b""))

    def _reply_error(self, query: zenoh.Query, message: str) -> None:
        data = message.encode("utf-8")
        try:
            query.reply_err(data, encoding=encoding_for(0))
        except zenoh.ZError as exc:
            log.debug("zenoh server %s: error reply failed: %s", self.endpoint, exc)
            return
        self._count_sent(len(data))

    # ------------------------------------------------------------------ observe

    def _publication(self, notify_key: str, gone: Callable[[], None]) -> _Publication | None:
        """A publisher on ``notify_key``, or None if Zenoh refuses one."""
        publisher = None
        try:
            publisher = self._session.declare_publisher(notify_key, congestion_control=zenoh.CongestionControl.BLOCK)
            return _Publication(self, notify_key, publisher, gone)
        except zenoh.ZError as exc:
            log.warning("zenoh server %s: cannot publish on %r: %s", self.endpoint, notify_key[:80], exc)
            if publisher is not None:
                with contextlib.suppress(zenoh.ZError):
                    publisher.undeclare()
            return None


class _Publication:
    """The way to one observer: a publisher on its notification key.

    Its matching status tells when the observer's subscriber is gone (its
    session closed, or it undeclared): then ``gone`` ends the observation."""

    def __init__(
        self, server: ZenohServerTransport, notify_key: str, publisher: zenoh.Publisher, gone: Callable[[], None]
    ) -> None:
        self._server = server
        self._notify_key = notify_key
        self._publisher = publisher
        self._gone = gone
        #: The observer's subscriber has been seen; losing it then ends the observation.
        self._matched = False
        loop = server._loop
        self._listener = publisher.declare_matching_listener(
            zenoh.handlers.Callback(lambda status: post(loop, self._matching, status.matching))
        )

    def _matching(self, matching: bool) -> None:
        if matching:
            self._matched = True
        elif self._matched:  # the observer's subscriber went away
            log.debug("zenoh server %s: observer of %s gone", self._server.endpoint, self._notify_key)
            self._gone()

    async def notify(self, response: Response, seq: int) -> bool:
        attachment = self._server._header(response, seq)
        try:
            self._publisher.put(response.payload, encoding=encoding_for(response.content_format), attachment=attachment)
        except zenoh.ZError as exc:
            log.debug("zenoh server %s: notification to %s failed: %s", self._server.endpoint, self._notify_key, exc)
            return False
        self._server._count_sent(len(self._notify_key) + len(response.payload) + len(attachment or b""))
        return True

    def close(self) -> None:
        with contextlib.suppress(zenoh.ZError):
            self._listener.undeclare()
        with contextlib.suppress(zenoh.ZError):
            self._publisher.undeclare()


# =========================================================================== client

#: How much later than the caller's deadline Zenoh times a query out itself.
_ZENOH_TIMEOUT_MARGIN_S = 0.5
#: How long a closing client waits for its sessions' goodbyes.
_CLOSE_WAIT_S = 2.0
#: Connection attempts of one client session, and the first back-off between them.
OPEN_ATTEMPTS = 3
OPEN_BACKOFF_S = 0.5


class _NoRoute(PeerUnreachable):
    """Zenoh ended a query without a reply before its timeout: no queryable
    reachable on that session (the peer's session is gone)."""


@dataclass(frozen=True)
class _Reply:
    """One reply or sample, copied out of Zenoh's objects on its thread."""

    ok: bool
    key: str
    payload: bytes
    encoding: str | None
    attachment: bytes | None

    @property
    def size(self) -> int:
        return len(self.key) + len(self.payload) + len(self.attachment or b"")


def _copy_reply(reply: zenoh.Reply) -> _Reply:
    if (sample := reply.ok) is not None:
        return _Reply(True, str(sample.key_expr), sample.payload.to_bytes(), str(sample.encoding), _bytes(sample.attachment))
    err = reply.err
    assert err is not None
    return _Reply(False, "", err.payload.to_bytes(), str(err.encoding), None)


def _copy_sample(sample: zenoh.Sample) -> _Reply:
    return _Reply(True, str(sample.key_expr), sample.payload.to_bytes(), str(sample.encoding), _bytes(sample.attachment))


class ZenohClientTransport(ClientCore):
    """Sends requests to Zenoh peers; one client-mode session per peer, opened lazily.

    Many requests may be in flight to the same peer; each is its own Zenoh
    query, so answers come back in any order."""

    def __init__(self, *, options: ZenohOptions | None = None, security: ZenohClientSecurity | None = None) -> None:
        """``security``: mTLS with the team's certificates
        (:mod:`coapkb.security.zenoh_tls`), or None."""
        self._options = options or ZenohOptions()
        super().__init__(self._options, log, "zenoh client")
        self._security = security
        # Threads start on first use, from the loop's thread: see the module doc.
        self._executor = ThreadPoolExecutor(max_workers=4, thread_name_prefix="zenoh client")
        self._sessions: dict[Endpoint, asyncio.Future[zenoh.Session]] = {}
        #: Names this client's notification keys: ``coapkb-obs/<id>/<n>``.
        self._id = os.urandom(6).hex()
        self._tokens = itertools.count()
        self._source_sn = itertools.count()

    # ------------------------------------------------------------------ sessions

    async def _session(self, peer: Endpoint) -> zenoh.Session:
        """The session to ``peer``, opened once however many wait for it.  A
        waiter that gives up (timeout) does not abort the opening."""
        self._check_open()
        check_scheme(peer, *LINK_PROTOCOLS)
        opening = self._sessions.get(peer)
        if opening is None or (opening.done() and (opening.cancelled() or opening.exception() is not None)):
            loop = asyncio.get_running_loop()
            opening = self._sessions[peer] = asyncio.ensure_future(
                loop.run_in_executor(self._executor, self._open, peer)
            )
        try:
            return await asyncio.shield(opening)
        except zenoh.ZError as exc:
            why = str(exc).split(' at ', 1)[0].strip()
            if self._security is not None:  # Zenoh does not say whether the TLS handshake failed
                why += " (over TLS with this team's certificates)"
            raise PeerUnreachable(f"cannot reach {peer}: {why}") from None

    def _config(self, peer: Endpoint) -> zenoh.Config:
        config = session_config("client", connect=(_secured_locator(peer, self._security),))
        if self._options.open_timeout_s is not None:
            config.insert_json5("transport/unicast/open_timeout", str(round(self._options.open_timeout_s * 1000)))
        if self._security is not None:
            self._security.configure(config)
        elif link_for(peer).needs_tls:  # QUIC's client verifies a chain: the anonymous listener's
            anonymous_tls.configure_connector(config)
        return config

    def _open(self, peer: Endpoint) -> zenoh.Session:
        """On the executor: open a session to ``peer`` and, with security,
        check that the member expected there is the one that answered.

        A client session makes one connection attempt.  On a slow lossy link
        the TLS and Zenoh handshakes of that attempt can fail (a robot's first
        query then failed, and with it its first task: traced in a bench run
        at 35 kbit/s and 15 % loss), so it is tried :data:`OPEN_ATTEMPTS` times,
        backing off; a refused TCP connection (a dead peer) fails at once each
        time, so finding a dead robot takes only the back-off longer (over
        QUIC nothing refuses: each attempt waits ``open_timeout_s``)."""
        for attempt in range(OPEN_ATTEMPTS):
            try:
                session = zenoh.open(self._config(peer))
                break
            except zenoh.ZError:
                if attempt == OPEN_ATTEMPTS - 1 or self._closed:
                    raise
                time.sleep(OPEN_BACKOFF_S * 2**attempt)  # on an executor thread: a back-off, not a wait
        if self._closed:  # the client closed while this session opened
            _close(session)
            raise TransportError("the zenoh client transport was closed")
        if self._security is not None:
            try:
                self._security.check_peer(session, peer)
            except BaseException:
                _close(session)
                raise
        return session

    # ------------------------------------------------------------------ one query

    def _query(
        self, session: zenoh.Session, request: Request, header: RequestHeader, timeout: float
    ) -> asyncio.Queue[_Reply | None]:
        """Send ``request`` as a Zenoh query; its replies arrive in the queue,
        then None when Zenoh ends the query (all answered, or its timeout)."""
        key = key_for_path(request.path)
        parameters = parameters_text(request.query)
        selector = f"{key}?{parameters}" if parameters else key
        attachment = encode_request_header(header)
        loop = asyncio.get_running_loop()
        replies: asyncio.Queue[_Reply | None] = asyncio.Queue()
        session.get(
            selector,
            zenoh.handlers.Callback(
                lambda reply: post(loop, replies.put_nowait, _copy_reply(reply)),
                lambda: post(loop, replies.put_nowait, None),
            ),
            payload=request.payload or None,
            encoding=encoding_for(request.content_format),
            attachment=attachment,
            timeout=timeout,
            # Names our session, whose link's certificate the server then
            # holds to the team's policy (coapkb.security.zenoh_tls).
            source_info=None if self._security is None else zenoh.SourceInfo(session.id, next(self._source_sn)),
        )
        self._count_sent(len(selector) + len(request.payload) + len(attachment or b""))
        return replies

    def _response(self, peer: Endpoint, reply: _Reply) -> Delivery:
        self._count_received(reply.size)
        if not reply.ok:  # the server could not read our query
            return Response(Status.BAD_REQUEST, reply.payload, 0), None
        try:
            return response_from_reply(reply.payload, reply.encoding, reply.attachment)
        except MappingError as exc:
            self._malformed(peer, str(exc))
            raise TransportError(f"malformed answer from {peer}: {exc}") from None

    async def _exchange(
        self,
        peer: Endpoint,
        request: Request,
        header: RequestHeader,
        timeout: float,
        session: zenoh.Session | None = None,
    ) -> Delivery:
        """One query and its first reply, within ``timeout`` (connecting included).

        Zenoh ends a query at once, without replies, when the session has no
        route to a queryable: its peer is gone.  The session is then closed
        (which also stops its reconnect attempts) and, within the time left,
        the query goes out once more on a fresh one: a peer that came back is
        answered at once, a dead one refuses the connection.  With a given
        ``session`` (an observation's, which holds its subscriber) there is
        no second try."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        attempts = 1 if session is not None else 2
        try:
            async with asyncio.timeout(timeout):
                for _ in range(attempts):
                    on = session if session is not None else await self._session(peer)
                    # Zenoh's own timeout a little later than ours, so an early
                    # end without replies always means "no route", never "slow".
                    zenoh_timeout = deadline - loop.time() + _ZENOH_TIMEOUT_MARGIN_S
                    try:
                        replies = self._query(on, request, header, zenoh_timeout)
                    except ValueError as exc:  # a path no key expression can carry
                        raise TransportError(f"cannot send {request.path!r} over zenoh: {exc}") from None
                    except zenoh.ZError as exc:
                        raise TransportError(f"query to {peer} failed: {exc}") from None
                    if (reply := await replies.get()) is not None:
                        return self._response(peer, reply)
                    self._drop_session(peer, on)
        except TimeoutError:
            raise PeerTimeout(f"no answer from {peer} within {timeout:g}s") from None
        except asyncio.CancelledError:
            if (err := self._closed_error()) is not None:
                raise err from None
            raise
        if self._security is not None:  # a query Zenoh's access control drops ends the same way
            raise _NoRoute(f"no answer from {peer}: its session is down, it serves no {KEY_ROOT}/**, "
                           f"or its access control refuses {request.path} to this member")
        raise _NoRoute(f"no answer from {peer}: its session is down or it serves no {KEY_ROOT}/**")

    def _drop_session(self, peer: Endpoint, session: zenoh.Session) -> None:
        """Forget ``session`` (the next request opens a new one) and close it in the background."""
        opening = self._sessions.get(peer)
        if opening is not None and opening.done() and not opening.cancelled() and opening.exception() is None:
            if opening.result() is session:
                del self._sessions[peer]
        if not session.is_closed():
            _close_in_thread(session)  # not awaited: the peer is gone, nobody waits for its goodbye

    # ------------------------------------------------------------------ API

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        """Send ``request`` to ``peer`` and return its answer.

        Raises :class:`PeerUnreachable` when ``peer`` cannot be connected to
        or no answer arrives within ``timeout`` seconds, and
        :class:`TransportError` for other failures (transport closed, a
        malformed answer)."""
        header = RequestHeader(request.method, request.accept, request.etags, if_match=request.if_match)
        response, _ = await self._exchange(peer, request, header, timeout)
        return response

    async def observe(
        self, peer: Endpoint, request: Request, *, timeout: float | None = None
    ) -> AsyncIterator[Response]:
        """The current representation, then one item per change.

        ``timeout`` (default ``options.observe_timeout_s``) bounds the wait
        for the first answer (:class:`PeerUnreachable`).  The iteration ends
        after the first item if the server did not register the observation
        (an error, or no slot left), and after an error notification.
        Closing the iterator deregisters.  If the peer dies the iterator just
        stops yielding, as with ZeroMQ.  Updates are coalesced: a slow reader
        sees the latest states, not necessarily every one."""
        timeout = self._options.observe_timeout_s if timeout is None else timeout
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        notify_key = f"{NOTIFY_ROOT}/{self._id}/{next(self._tokens)}"
        notifications: asyncio.Queue[_Reply | TransportError] = asyncio.Queue(maxsize=self._options.observe_queue)
        with self._observation(notifications):
            header = RequestHeader(request.method, request.accept, request.etags, Observe.REGISTER, notify_key)
            session, subscriber, response, seq = None, None, None, None
            # As in _exchange: once more on a fresh session if the first had no
            # route; the subscriber must live on the session the query goes out on.
            for attempt in range(2):
                try:
                    async with asyncio.timeout(max(deadline - loop.time(), 0.0)):
                        session = await self._session(peer)
                except TimeoutError:
                    raise PeerTimeout(f"no answer from {peer} within {timeout:g}s") from None
                try:
                    subscriber = session.declare_subscriber(notify_key, zenoh.handlers.Callback(
                        lambda sample: post(loop, put_latest, notifications, _copy_sample(sample))))
                except zenoh.ZError as exc:
                    raise TransportError(f"cannot subscribe to notifications from {peer}: {exc}") from None
                try:
                    response, seq = await self._exchange(peer, request, header, max(deadline - loop.time(), 0.0), session)
                    break
                except _NoRoute:
                    with contextlib.suppress(zenoh.ZError):
                        subscriber.undeclare()
                    if attempt:
                        raise
                except BaseException:
                    with contextlib.suppress(zenoh.ZError):
                        subscriber.undeclare()
                    raise
            assert session is not None and subscriber is not None and response is not None
            state = ObserverState(response, seq)
            try:
                yield response
                while state.registered:
                    sample = state.delivered(await notifications.get())
                    try:
                        response, seq = self._response(peer, sample)
                    except TransportError:
                        continue  # counted; a garbled notification is skipped like a lost one
                    # A notification that arrived before the registration's answer is stale.
                    if state.accept(response, seq):
                        yield response
            finally:
                with contextlib.suppress(zenoh.ZError):
                    subscriber.undeclare()
                if state.registered and not self._closed:
                    self._deregister(session, request, notify_key)

    def _deregister(self, session: zenoh.Session, request: Request, notify_key: str) -> None:
        """Best effort, not awaited: the server also ends the observation when it
        sees our subscriber gone (its publisher's matching status)."""
        header = RequestHeader(request.method, observe=Observe.DEREGISTER, notify_key=notify_key)
        with contextlib.suppress(zenoh.ZError, ValueError):
            self._query(session, Request(request.method, request.path), header, 1.0)

    async def aclose(self) -> None:
        """Close every session (pending requests then fail with
        :class:`PeerUnreachable` or :class:`TransportError`).  Idempotent."""
        if self._closed:
            return
        self._closed = True
        sessions = []
        for opening in self._sessions.values():
            # One still opening is not waited for (to a dead QUIC peer that is
            # Zenoh's open timeout, 10 s): _open closes it when it comes.
            if opening.done() and not opening.cancelled() and opening.exception() is None:
                sessions.append(opening.result())
        self._sessions.clear()
        self._end_observations()
        closing = [_close_in_thread(session) for session in sessions if not session.is_closed()]
        if closing:
            # Live peers are told goodbye within milliseconds; a session still
            # retrying a peer that left is not waited for (_close_in_thread).
            await asyncio.wait(closing, timeout=_CLOSE_WAIT_S)
        self._executor.shutdown(wait=False)
