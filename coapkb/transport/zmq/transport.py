"""ZeroMQ/TCP transport: the seed paper's transport behind coapkb's interface.

The agent and the benchmarks talk to :class:`~coapkb.transport.base.ClientTransport`
and :class:`~coapkb.transport.base.ServerTransport`; this module implements both
over ZeroMQ so the CoAP/UDP transport can be compared against the paper's
original choice with everything else held equal.

Sockets and envelope
    The server binds one ROUTER socket; a client opens one DEALER socket per
    peer, lazily, on first use.  Each request and each response is a single
    ZeroMQ frame holding the CBOR envelope of :mod:`.zmq_wire` (token, CoAP
    method/status codes, options, payload).  DEALER/ROUTER rather than REQ/REP
    because REQ/REP allows one outstanding request per socket and wedges when
    an answer is lost; with DEALER/ROUTER many requests are in flight at once
    and replies are matched by token, like CoAP.

Unreachable peers
    libzmq connects in the background and retries for ever; by default it also
    queues messages for a peer it has never reached and sends them whenever the
    connection finally comes up -- minutes later, to a robot that no longer
    wants the answer.  The client therefore sets ``ZMQ_IMMEDIATE`` (messages are
    only queued on completed connections; a send waits, within the request's
    timeout, for one to exist), ``LINGER=0`` (nothing is kept after close) and a
    small ``SNDHWM``.  A request whose send did not even get out before the
    timeout raises :class:`PeerUnreachable`, and when nobody else uses that
    peer's socket it is closed, which stops libzmq's reconnect attempts (SYNs
    every ``reconnect_ivl_max`` on the radio) until the peer is asked again.

Liveness
    TCP keep-alive (a client after 30 s idle, a server after 120 s, then 10
    probes 1 s apart) and ``TCP_USER_TIMEOUT`` (via ``ZMQ_TCP_MAXRT``, 60 s)
    let both ends notice a robot that drove out of range instead of waiting
    for the kernel's defaults (2 h / ~15 min), without cutting healthy
    connections on a link that loses 20 % of its packets (a cut connection
    loses the request in flight), and without filling a slow link with
    probes.
    Reconnects start after 100 ms and back off to 2 s.  Clients set a random
    routing id and the server sets ``ROUTER_HANDOVER`` so a client that
    reconnects before the server noticed its old connection die takes over its
    identity (and its observations) instead of being refused.  ZMTP heartbeats
    are off by default because they cost payload bytes on slow links; see
    :class:`ZmqOptions`.

Observe
    A request carrying the envelope's observe flag registers ``(client
    identity, token)`` in the server's
    :class:`~coapkb.transport.observation.ObservationRegistry`, which
    subscribes through :meth:`Service.subscribe`.  Each change re-runs
    the request through :meth:`Service.handle` and pushes the answer with the
    next ``seq``.  Changes that arrive while an update is being computed are
    coalesced (an observer gets the latest state, not every intermediate one,
    as in RFC 7641).  An error answer ends the observation.  The client ends
    it with a deregistration when its iterator is closed; a client that
    vanishes is forgotten as soon as a push to it fails (``ROUTER_MANDATORY``
    reports its route gone once TCP closed the connection).

Traffic counters
    Count the bytes each message occupies in the TCP byte stream: the envelope
    plus its ZMTP frame header (2 bytes, or 9 above 255 bytes); checked against
    a counting TCP proxy, they match the stream exactly except for the ZMTP
    handshake (115 bytes client to server, 107 back, once per connection).
    Not counted here: that handshake, heartbeats, TCP/IP headers, ACKs and
    keep-alive probes -- the link emulator counts those.
    TCP retransmits invisibly, so ``retransmissions`` stays 0.
"""

from __future__ import annotations

import asyncio
import errno
import itertools
import logging
import os
from collections.abc import AsyncIterator
from dataclasses import dataclass

import zmq
import zmq.asyncio

from ..base import (
    Endpoint,
    PeerTimeout,
    RateLimitedLog,
    Service,
    TransportError,
)
from ..core import ClientCore, CoreOptions, ServerCore, check_scheme
from ..envelope import (
    MAX_TOKEN,
    Observe,
    WireError,
    decode_request,
    decode_response,
    encode_request,
)
from ..messages import Request, Response
from ..observation import Delivery, ObserverState, put_latest
from .security import ZmqClientSecurity, ZmqServerSecurity

__all__ = [
    "ZmqOptions",
    "ZmqServerTransport",
    "ZmqClientTransport",
    "zmtp_frame_bytes",
]

log = logging.getLogger(__name__)

def zmtp_frame_bytes(size: int) -> int:
    """Bytes a message frame of ``size`` bytes takes in a ZMTP 3 stream
    (flags octet plus a 1-octet length, or an 8-octet one above 255)."""
    return size + (2 if size <= 255 else 9)


@dataclass(frozen=True)
class ZmqOptions(CoreOptions):
    """Socket tuning shared by client and server.  Defaults suit robots on Wi-Fi."""

    #: First reconnect after a lost/refused connection, then doubling up to the max.
    reconnect_ivl_ms: int = 100
    reconnect_ivl_max_ms: int = 2000
    #: Give up a TCP connect after this long and start again (the kernel
    #: retries the SYN meanwhile, 1, 3, 7 ... 63 s after it).  Every attempt
    #: given up costs the server the SYN-ACKs it keeps sending for it: at
    #: 3 s, 99 robots' connects to a central server on a 35 kbit/s link gave
    #: up while its SYN-ACKs waited in its queue, 8,305 attempts whose 13,304
    #: SYN-ACK retransmissions filled its uplink (163 of 165 tasks
    #: unavailable); at 30 s, 1,318 attempts and 9,341 (140 unavailable).
    #: A request to a peer that refuses fails at once anyway.
    connect_timeout_ms: int = 120_000
    #: A connection must finish the ZMTP handshake within this time.  At 5 s,
    #: 30 clients' CurveZMQ handshakes through a central server's 35 kbit/s
    #: link ran out, were dropped and started again, and 29 of them never
    #: carried an answer; libzmq's 30 s ran out for 99.
    handshake_ivl_ms: int = 120_000
    #: Kernel keep-alive: first probe after idle seconds, then every intvl, give up after cnt.
    #: At 20 % loss each way a probe's round trip fails 36 % of the time, so 3
    #: probes would kill ~5 % of healthy idle connections (and the request in
    #: flight with them); 10 probes kill 4e-5.  Each probe and its answer
    #: cross the link: at 5 s idle, a central server's 100 connections spent
    #: about 40 % of its 35 kbit/s uplink on them, and at 99 robots the queue
    #: behind them made every query outlast its timeout.  A client probes
    #: after 30 s, a server (which only needs to forget a vanished client's
    #: observations) after ``server_tcp_keepalive_idle_s``.
    tcp_keepalive_idle_s: int = 30
    server_tcp_keepalive_idle_s: int = 120
    tcp_keepalive_intvl_s: int = 1
    tcp_keepalive_cnt: int = 10
    #: TCP_USER_TIMEOUT: drop a connection whose sent data stays unacknowledged
    #: this long.  TCP's own backoff on a lossy link (0.2, 0.4, ... 6.4 s) must
    #: fit well inside it, so a slow-but-alive peer is not cut off.
    tcp_user_timeout_ms: int = 60_000
    #: ZMTP PING interval (0 = off).  Costs ~16 payload bytes per interval and peer.
    heartbeat_ivl_ms: int = 0
    heartbeat_timeout_ms: int = 6000
    #: Client: messages queued per peer before ``request`` waits (within its
    #: timeout).  Small, so requests to a wedged peer are not hoarded and
    #: delivered long after their callers gave up.
    client_sndhwm: int = 100
    #: Server: answers queued per client; beyond it answers to that client are
    #: dropped (it is not reading) rather than stalling everyone else.
    server_sndhwm: int = 1000
    #: Messages queued per peer on receipt; when full, libzmq stops reading
    #: that TCP connection (flow control back to the sender).
    rcvhwm: int = 1000
    #: Largest request the server accepts (libzmq drops the connection otherwise).
    max_request_bytes: int = 1 << 20
    #: Largest response a client accepts (-1: no limit; results can be big).
    max_response_bytes: int = -1
    #: Server: observations one client identity may hold.
    max_observations: int = 16


def _configure(sock: zmq.asyncio.Socket, options: ZmqOptions, host: str, *, keepalive_idle_s: int) -> None:
    """Options common to both ends; must run before bind/connect.

    IPv6 is enabled only for IPv6 literals: with it on, libzmq may resolve a
    host name to an IPv6 address the peer does not listen on, and it does not
    fall back to the IPv4 one."""
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RECONNECT_IVL, options.reconnect_ivl_ms)
    sock.setsockopt(zmq.RECONNECT_IVL_MAX, options.reconnect_ivl_max_ms)
    sock.setsockopt(zmq.HANDSHAKE_IVL, options.handshake_ivl_ms)
    sock.setsockopt(zmq.TCP_KEEPALIVE, 1)
    sock.setsockopt(zmq.TCP_KEEPALIVE_IDLE, keepalive_idle_s)
    sock.setsockopt(zmq.TCP_KEEPALIVE_INTVL, options.tcp_keepalive_intvl_s)
    sock.setsockopt(zmq.TCP_KEEPALIVE_CNT, options.tcp_keepalive_cnt)
    sock.setsockopt(zmq.TCP_MAXRT, options.tcp_user_timeout_ms)
    sock.setsockopt(zmq.RCVHWM, options.rcvhwm)
    if options.heartbeat_ivl_ms > 0:
        sock.setsockopt(zmq.HEARTBEAT_IVL, options.heartbeat_ivl_ms)
        sock.setsockopt(zmq.HEARTBEAT_TIMEOUT, options.heartbeat_timeout_ms)
    if ":" in host:
        sock.setsockopt(zmq.IPV6, 1)


def _tcp_uri(host: str, port: int | str) -> str:
    return f"tcp://[{host}]:{port}" if ":" in host else f"tcp://{host}:{port}"


# =========================================================================== server


class ZmqServerTransport(ServerCore):
    """Serves a :class:`Service` on a ZeroMQ ROUTER socket.

    Create with :meth:`start`.  Requests are handled concurrently (at most
    ``options.max_concurrent_requests`` at once; beyond that the receive loop
    stops reading, so TCP flow control pushes back on the clients instead of
    the server buffering without bound).  Malformed messages are counted in
    :attr:`malformed` and dropped.
    """

    def __init__(
        self,
        service: Service,
        endpoint: Endpoint,
        sock: zmq.asyncio.Socket,
        context: zmq.asyncio.Context,
        owns_context: bool,
        options: ZmqOptions,
        security: ZmqServerSecurity | None = None,
    ) -> None:
        """Private: use :meth:`start`, which binds the socket first."""
        super().__init__(service, endpoint, options, log, "zmq server")
        #: Authenticates clients (CurveZMQ), or None.
        self._security = security
        self._sock = sock
        self._ctx = context
        self._owns_context = owns_context
        self._send_log = RateLimitedLog(log, options.malformed_log_interval_s)
        self._receiver = asyncio.create_task(self._receive_loop(), name=f"zmq server {endpoint}")

    @classmethod
    async def start(
        cls,
        service: Service,
        endpoint: Endpoint,
        *,
        options: ZmqOptions | None = None,
        context: zmq.asyncio.Context | None = None,
        security: ZmqServerSecurity | None = None,
    ) -> ZmqServerTransport:
        """Bind ``tcp://host:port`` and start serving.

        Port 0 picks a free port; the returned transport's :attr:`endpoint`
        has the real one.  The host is an IPv4 or IPv6 literal, an interface
        name, or ``*`` for all IPv4 interfaces (``::`` for IPv6 and IPv4).
        A shared ``context`` is left open on :meth:`aclose`; otherwise the
        transport owns (and terminates) its own.  Raises
        :class:`TransportError` if the address cannot be bound (port in use,
        no such interface).
        """
        check_scheme(endpoint, "zmq")
        options = options or ZmqOptions()
        ctx = context if context is not None else zmq.asyncio.Context()
        sock = ctx.socket(zmq.ROUTER)
        try:
            _configure(sock, options, endpoint.host, keepalive_idle_s=options.server_tcp_keepalive_idle_s)
            sock.setsockopt(zmq.SNDHWM, options.server_sndhwm)
            sock.setsockopt(zmq.ROUTER_MANDATORY, 1)
            sock.setsockopt(zmq.ROUTER_HANDOVER, 1)
            sock.setsockopt(zmq.MAXMSGSIZE, options.max_request_bytes)
            if security is not None:
                security.configure(sock, ctx)
            sock.bind(_tcp_uri(endpoint.host, endpoint.port or "*"))
            bound = sock.getsockopt_string(zmq.LAST_ENDPOINT)
        except zmq.ZMQError as exc:
            sock.close(linger=0)
            if context is None:
                ctx.term()
            if exc.errno == errno.EADDRINUSE:
                raise TransportError(f"cannot listen on {endpoint}: port {endpoint.port} is already in use") from exc
            raise TransportError(f"cannot listen on {endpoint}: {exc}") from exc
        port = int(bound.rsplit(":", 1)[1])
        return cls(service, Endpoint("zmq", endpoint.host, port), sock, ctx, context is None, options, security)

    def _stop_receiving(self) -> None:
        self._receiver.cancel()

    async def _close_transport(self) -> None:
        """Close the socket (linger 0: unsent answers are discarded)."""
        await asyncio.gather(self._receiver, return_exceptions=True)
        self._sock.close(linger=0)
        if self._security is not None:
            self._security.stop()
        if self._owns_context:
            self._ctx.term()

    # ------------------------------------------------------------------ receiving

    async def _receive_loop(self) -> None:
        sock = self._sock
        while True:
            user: str | None = None
            try:
                if self._security is None:
                    frames = await sock.recv_multipart()
                else:
                    # CURVE: the ZAP handler named the member; libzmq hands it over as frame metadata.
                    raw = await sock.recv_multipart(copy=False)
                    named = raw[-1].get("User-Id") if len(raw) > 1 else None
                    user = named if isinstance(named, str) else None
                    frames = [frame.bytes for frame in raw]
            except zmq.ZMQError as exc:
                if self._closed or exc.errno in (zmq.ETERM, zmq.ENOTSOCK):
                    return
                self._bad_log.warning("zmq server %s: receive failed: %s", self.endpoint, exc)
                continue
            identity, body = frames[0], frames[1:]
            self._count_received(sum(zmtp_frame_bytes(len(f)) for f in body))
            if len(body) != 1:
                self._malformed(f"peer {identity.hex()}", f"{len(body)} frames, expected 1")
                continue
            try:
                token, request, observe = decode_request(body[0])
            except WireError as exc:
                self._malformed(f"peer {identity.hex()}", str(exc))
                continue
            if observe is Observe.DEREGISTER:
                self._observations.deregister(identity, token)
                continue
            await self._slots.acquire()
            self._spawn(self._serve(identity, token, request, observe, user))

    # ------------------------------------------------------------------ answering

    async def _serve(self, identity: bytes, token: int, request: Request, observe: Observe,
                     user: str | None = None) -> None:
        """One request; holds a concurrency slot (taken by the receive loop)."""
        try:
            push = _Push(self, identity, token)
            sender = None if self._security is None else self._security.sender(user)
            await self._answer(request, push.send, sender=sender,
                               observe=(identity, token) if observe is Observe.REGISTER else None,
                               notifier=lambda gone: push)
        finally:
            self._slots.release()

    async def _send(self, identity: bytes, data: bytes) -> bool:
        """Queue one message for ``identity``; never waits.

        False if it could not be queued: the peer is gone (then its
        observations are dropped) or is not reading (its queue is full; the
        message is dropped like a lost datagram rather than stalling every
        other client behind it).
        """
        try:
            await self._sock.send_multipart([identity, data], flags=zmq.NOBLOCK)
        except zmq.Again:
            self._send_log.warning(
                "zmq server %s: peer %s is not reading; dropped a message", self.endpoint, identity.hex()
            )
            return False
        except zmq.ZMQError as exc:
            if exc.errno == zmq.EHOSTUNREACH:
                log.debug("zmq server %s: peer %s is gone", self.endpoint, identity.hex())
                self._observations.forget_client(identity)
            elif not self._closed:
                self._send_log.warning("zmq server %s: send to %s failed: %s", self.endpoint, identity.hex(), exc)
            return False
        self._count_sent(zmtp_frame_bytes(len(data)))
        return True


@dataclass(frozen=True)
class _Push:
    """The way to one observer: messages to its identity, under its token.

    A peer that is gone is found out by the send itself, which forgets it
    with all its observations (``ROUTER_MANDATORY``)."""

    server: ZmqServerTransport
    identity: bytes
    token: int

    async def send(self, response: Response, seq: int | None) -> bool:
        """Queue one answer; False if it could not be (see :meth:`ZmqServerTransport._send`)."""
        return await self.server._send(self.identity, self.server._encoded(self.token, response, seq))

    async def notify(self, response: Response, seq: int) -> bool:
        # A notification that could not be queued is dropped like a lost
        # datagram; a peer that is gone has already been forgotten.
        await self.send(response, seq)
        return True

    def close(self) -> None:
        """Nothing to release: the socket is the server's."""


# =========================================================================== client


def _new_routing_id() -> bytes:
    """8 random bytes; libzmq reserves ids starting with a zero byte."""
    rid = os.urandom(8)
    return rid if rid[0] else b"\x01" + rid[1:]


class _PeerLink:
    """One DEALER socket to one peer, its reader task and whoever waits on it."""

    def __init__(self, peer: Endpoint, sock: zmq.asyncio.Socket, client: ZmqClientTransport) -> None:
        self.peer = peer
        self.sock = sock
        self.pending: dict[int, asyncio.Future[Delivery]] = {}
        self.observers: dict[int, asyncio.Queue[Delivery | TransportError]] = {}
        #: Requests and observe set-ups currently using the socket.
        self.users = 0
        self.closed = False
        self._client = client
        self._tokens = itertools.count()
        self.reader = asyncio.create_task(self._read(), name=f"zmq client reader {peer}")

    def new_token(self) -> int:
        return next(self._tokens) & MAX_TOKEN

    def close(self) -> None:
        """Close now (linger 0: whatever is still queued is discarded)."""
        if self.closed:
            return
        self.closed = True
        self.reader.cancel()
        self.sock.close(linger=0)

    async def _read(self) -> None:
        while True:
            try:
                frames = await self.sock.recv_multipart()
            except zmq.ZMQError as exc:
                if self.closed or exc.errno in (zmq.ETERM, zmq.ENOTSOCK):
                    return
                self._client._bad_log.warning("zmq client: receive from %s failed: %s", self.peer, exc)
                continue
            self._client._count_received(sum(zmtp_frame_bytes(len(f)) for f in frames))
            if len(frames) != 1:
                self._client._malformed(self.peer, f"{len(frames)} frames, expected 1")
                continue
            try:
                token, response, seq = decode_response(frames[0])
            except WireError as exc:
                self._client._malformed(self.peer, str(exc))
                continue
            if (fut := self.pending.get(token)) is not None:
                if not fut.done():
                    fut.set_result((response, seq))
            elif (queue := self.observers.get(token)) is not None:
                put_latest(queue, (response, seq))
            else:
                log.debug("zmq client: late answer for token %d from %s dropped", token, self.peer)


class ZmqClientTransport(ClientCore):
    """Sends requests to ZeroMQ peers; one DEALER socket per peer, opened lazily.

    Many requests may be in flight to the same peer; answers are matched by
    token, so they may come back in any order.
    """

    def __init__(
        self,
        *,
        options: ZmqOptions | None = None,
        context: zmq.asyncio.Context | None = None,
        security: ZmqClientSecurity | None = None,
    ) -> None:
        """A shared ``context`` is left open on :meth:`aclose`; otherwise the
        transport owns and terminates its own.  ``security``: CurveZMQ
        (:mod:`coapkb.security.curve`), or None."""
        self._options = options or ZmqOptions()
        super().__init__(self._options, log, "zmq client")
        self._security = security
        self._owns_context = context is None
        self._ctx = context if context is not None else zmq.asyncio.Context()
        self._links: dict[Endpoint, _PeerLink] = {}
        self._closing_readers: set[asyncio.Task[None]] = set()

    # ------------------------------------------------------------------ sockets

    def _link(self, peer: Endpoint) -> _PeerLink:
        self._check_open()
        check_scheme(peer, "zmq")
        link = self._links.get(peer)
        if link is not None:
            return link
        sock = self._ctx.socket(zmq.DEALER)
        try:
            _configure(sock, self._options, peer.host, keepalive_idle_s=self._options.tcp_keepalive_idle_s)
            sock.setsockopt(zmq.IMMEDIATE, 1)
            sock.setsockopt(zmq.SNDHWM, self._options.client_sndhwm)
            sock.setsockopt(zmq.ROUTING_ID, _new_routing_id())
            sock.setsockopt(zmq.CONNECT_TIMEOUT, self._options.connect_timeout_ms)
            sock.setsockopt(zmq.MAXMSGSIZE, self._options.max_response_bytes)
            if self._security is not None:
                self._security.configure(sock, peer)
            sock.connect(_tcp_uri(peer.host, peer.port))
        except zmq.ZMQError as exc:
            sock.close(linger=0)
            raise TransportError(f"cannot connect to {peer}: {exc}") from exc
        except BaseException:
            sock.close(linger=0)
            raise
        link = self._links[peer] = _PeerLink(peer, sock, self)
        return link

    def _release(self, link: _PeerLink, *, got_out: bool) -> None:
        """A user is done with ``link``.  If its message never got out (no
        connection within the timeout) and nobody else uses the socket, close
        it: that stops libzmq reconnecting to a dead peer for ever."""
        link.users -= 1
        if got_out or link.users or link.observers or link.closed:
            return
        if self._links.get(link.peer) is link:
            del self._links[link.peer]
        link.close()
        self._closing_readers.add(link.reader)
        link.reader.add_done_callback(self._closing_readers.discard)

    # ------------------------------------------------------------------ API

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        """Send ``request`` to ``peer`` and return its answer.

        Raises :class:`PeerUnreachable` when no answer arrives within
        ``timeout`` seconds -- whether the peer is down, unreachable, or just
        slow -- and :class:`TransportError` if the transport is closed meanwhile.
        """
        link = self._link(peer)
        token = link.new_token()
        data = encode_request(request, token=token)
        fut: asyncio.Future[Delivery] = asyncio.get_running_loop().create_future()
        link.pending[token] = fut
        link.users += 1
        got_out = False
        try:
            async with asyncio.timeout(timeout):
                await link.sock.send(data)  # waits for a connection (ZMQ_IMMEDIATE)
                got_out = True
                self._count_sent(zmtp_frame_bytes(len(data)))
                response, _ = await fut
                return response
        except TimeoutError:
            raise PeerTimeout(f"no answer from {peer} within {timeout:g}s") from None
        except asyncio.CancelledError:
            if (err := self._closed_error()) is not None:
                raise err from None
            raise
        except zmq.ZMQError as exc:
            raise TransportError(f"request to {peer} failed: {exc}") from exc
        finally:
            link.pending.pop(token, None)
            self._release(link, got_out=got_out)

    async def observe(
        self, peer: Endpoint, request: Request, *, timeout: float | None = None
    ) -> AsyncIterator[Response]:
        """The current representation, then one item per change.

        ``timeout`` (default ``options.observe_timeout_s``) bounds the wait for
        the first answer (:class:`PeerUnreachable`).  The iteration ends after
        the first item if the server did not register the observation (error
        status, or it has no observer slot left), and after an error
        notification.  Closing the iterator (``break``, ``aclose()``; prefer
        ``contextlib.aclosing`` to make it immediate) deregisters.  If the peer
        dies the iterator just stops yielding; callers wanting liveness should
        wrap their reads in a timeout.  Updates are coalesced: a slow reader
        sees the latest states, not necessarily every one.
        """
        timeout = self._options.observe_timeout_s if timeout is None else timeout
        link = self._link(peer)
        token = link.new_token()
        queue: asyncio.Queue[Delivery | TransportError] = asyncio.Queue(maxsize=self._options.observe_queue)
        link.observers[token] = queue
        link.users += 1
        got_out = False
        state: ObserverState | None = None
        # An observation of a client that closes ends with its TransportError (ClientCore).
        with self._observation(queue):
            try:
                try:
                    async with asyncio.timeout(timeout):
                        data = encode_request(request, token=token, observe=Observe.REGISTER)
                        await link.sock.send(data)
                        got_out = True
                        self._count_sent(zmtp_frame_bytes(len(data)))
                        item = await queue.get()
                except TimeoutError:
                    raise PeerTimeout(f"no answer from {peer} within {timeout:g}s") from None
                except asyncio.CancelledError:
                    if (err := self._closed_error()) is not None:
                        raise err from None
                    raise
                except zmq.ZMQError as exc:
                    raise TransportError(f"observe request to {peer} failed: {exc}") from exc
                finally:
                    if not got_out:
                        link.observers.pop(token, None)  # so _release may close the socket
                    self._release(link, got_out=got_out)
                if isinstance(item, TransportError):
                    raise item
                response, seq = item
                state = ObserverState(response, seq)
                yield response
                while state.registered:
                    response, seq = state.delivered(await queue.get())
                    if state.accept(response, seq):
                        yield response
            finally:
                link.observers.pop(token, None)
                if state is not None and state.registered and not link.closed:
                    await self._deregister(link, token, request)

    async def _deregister(self, link: _PeerLink, token: int, request: Request) -> None:
        """Best effort: a lost deregistration is cleaned up by the server at the
        latest when its next push to us fails after the connection closed.
        Only the token matters to the server, so query and payload are left out."""
        data = encode_request(Request(request.method, request.path), token=token, observe=Observe.DEREGISTER)
        try:
            async with asyncio.timeout(1.0):
                await link.sock.send(data, flags=zmq.NOBLOCK)
        except (zmq.ZMQError, TimeoutError) as exc:
            log.debug("zmq client: deregistration to %s not sent: %s", link.peer, exc)
        else:
            self._count_sent(zmtp_frame_bytes(len(data)))

    async def aclose(self) -> None:
        """Fail pending requests and observations with :class:`TransportError`
        and close every socket (linger 0).  Idempotent."""
        if self._closed:
            return
        self._closed = True
        readers = list(self._closing_readers)
        closed = TransportError("the zmq client transport was closed")
        for link in self._links.values():
            for fut in link.pending.values():
                if not fut.done():
                    fut.set_exception(closed)
            link.close()
            readers.append(link.reader)
        self._links.clear()
        self._end_observations()
        await asyncio.gather(*readers, return_exceptions=True)
        if self._owns_context:
            self._ctx.term()
