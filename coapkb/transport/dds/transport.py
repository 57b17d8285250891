"""DDS transport: a robot's resources behind DDS topics (Cyclone DDS).

:class:`DdsServerTransport` is one participant in a Cyclone domain of its
own, on its endpoint's port; it reads every client's requests from
``coapkb_rq_S`` and answers each client on ``coapkb_rp_S_C`` and, for
observations, ``coapkb_nt_S_C``.  :class:`DdsClientTransport` opens one
participant per peer, lazily, whose only configured peer is that server,
and waits for its writer to match (re-announcing itself with a back-off
meanwhile) before it sends.  Every sample is one :class:`Envelope`: a 64-bit
key and the CBOR envelope ZeroMQ carries (:mod:`coapkb.transport.envelope`).
Reliability is RTPS's own; the transport never repeats a request.  How an
endpoint becomes a Cyclone domain (ports, peers, discovery) is :mod:`.config`.

Cyclone calls listeners from its own threads; they only hand the event to
the loop (``call_soon_threadsafe``).  Domains are created on the loop's
thread, so Cyclone's sockets belong to that thread's network namespace.

docs/dds.md specifies the rest, with the reasons: addressing, topics and
QoS, discovery, the settings for a slow radio, errors
(:class:`PeerUnreachable`), Observe, security (none: the wheel has no DDS
Security) and what the traffic counters hold.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import itertools
import logging
import os
import socket
import threading
from collections import OrderedDict
from collections.abc import AsyncIterator
from dataclasses import dataclass

from cyclonedds.core import DDSException, Entity, Listener, Policy, Qos
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.internal import load_cyclonedds
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from ..base import (
    Endpoint,
    PeerTimeout,
    PeerUnreachable,
    Service,
    TransportError,
    free_port,
)
from ..core import ClientCore, CoreOptions, ServerCore, check_scheme, post
from ..envelope import (
    Observe,
    WireError,
    decode_request,
    decode_response,
    encode_request,
)
from ..messages import Request, Response
from ..observation import Delivery, ObserverState, put_latest
from .config import DomainSettings, client_domain_xml, local_address_towards, server_domain_xml, topic_names
from .envelope import KEY_BYTES, Envelope

__all__ = ["DdsClientTransport", "DdsOptions", "DdsServerTransport", "Envelope"]

log = logging.getLogger(__name__)

# Cyclone prints a warning for every malformed datagram, without limit: a
# peer spraying garbage would flood stderr.  Its errors stay on.
_DDS_LC_FATAL, _DDS_LC_ERROR = 1, 2
load_cyclonedds().dds_set_log_mask(_DDS_LC_FATAL | _DDS_LC_ERROR)

@dataclass(frozen=True)
class DdsOptions(CoreOptions):
    """Limits shared by client and server."""

    #: Server: clients it keeps reply writers for (the least recently heard-from goes first).
    max_clients: int = 256
    #: Client: first and longest pause between SPDP re-announcements while a peer is not yet discovered.
    rediscover_first_s: float = 0.25
    rediscover_max_s: float = 4.0
    #: Requests and replies kept per writer (KEEP_LAST) until acknowledged.
    history_depth: int = 64
    settings: DomainSettings = DomainSettings()


def _qos(depth: int, *, transient: bool) -> Qos:
    return Qos(
        Policy.Reliability.Reliable(duration(seconds=1)),
        Policy.History.KeepLast(depth),
        Policy.Durability.TransientLocal if transient else Policy.Durability.Volatile,
    )


def _port_taken(address: str, port: int) -> bool:
    """Whether another socket holds UDP ``port`` on ``address``."""
    family = socket.AF_INET6 if ":" in address else socket.AF_INET
    with socket.socket(family, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind((address, port))
        except OSError as exc:
            return exc.errno == errno.EADDRINUSE
    return False


def _resolve(host: str) -> str:
    """A numeric address for ``host`` (Cyclone binds interfaces by address)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        return str(socket.getaddrinfo(host, None, family, socket.SOCK_DGRAM)[0][4][0])
    except socket.gaierror as exc:
        raise TransportError(f"cannot resolve {host!r}: {exc}") from None


def _delete(entity: Entity | None) -> None:
    """Delete a Cyclone entity (and its children) now, not when Python collects it."""
    if entity is None:
        return
    ref = getattr(entity, "_ref", None)
    if ref is None or Entity._entities.pop(ref, None) is None:
        return
    with contextlib.suppress(DDSException):
        entity._delete(ref)


class _Domains:
    """In-process Cyclone domain ids: each domain instance needs its own
    (they all use external domain id 0 on the wire)."""

    _lock = threading.Lock()
    _used: set[int] = set()

    @classmethod
    def take(cls) -> int:
        with cls._lock:
            for candidate in range(1, 231):
                if candidate not in cls._used:
                    cls._used.add(candidate)
                    return candidate
        raise TransportError("too many DDS domains in this process (230)")

    @classmethod
    def give_back(cls, domain_id: int) -> None:
        with cls._lock:
            cls._used.discard(domain_id)


class _Participant:
    """One Cyclone domain and its one participant."""

    def __init__(self, xml: str) -> None:
        self.domain_id = _Domains.take()
        try:
            self.domain = Domain(self.domain_id, xml)
            self.participant = DomainParticipant(self.domain_id)
        except DDSException as exc:
            _Domains.give_back(self.domain_id)
            raise TransportError(f"cannot start a DDS participant: {exc}") from None
        self._topics: dict[str, Topic] = {}
        self._userdata = itertools.count(1)

    def topic(self, name: str) -> Topic:
        if name not in self._topics:
            self._topics[name] = Topic(self.participant, name, Envelope)
        return self._topics[name]

    def announce(self) -> None:
        """Re-send this participant's SPDP announcement to its peers now
        (Cyclone republishes at once when the participant's QoS changes)."""
        with contextlib.suppress(DDSException):
            self.participant.set_qos(Qos(Policy.Userdata(next(self._userdata).to_bytes(4, "big"))))

    def close(self) -> None:
        self._topics.clear()
        _delete(self.participant)
        _delete(self.domain)
        _Domains.give_back(self.domain_id)


def _take(reader: DataReader) -> list[tuple[int, bytes]]:
    """Every sample with data waiting in ``reader``: (key, envelope bytes)."""
    out: list[tuple[int, bytes]] = []
    while True:
        try:
            samples = reader.take(64)
        except DDSException:
            return out
        if not samples:
            return out
        # Instance-state changes (a writer gone: NOT_ALIVE_NO_WRITERS) come as samples without data.
        out.extend((int(s.id), bytes(s.body)) for s in samples if isinstance(s, Envelope))


# =========================================================================== server


class _ClientWriters:
    """A server's writers towards one client."""

    def __init__(self, server: DdsServerTransport, client: int) -> None:
        names = topic_names(server.endpoint.host, server.endpoint.port, client)
        part = server._participant
        depth = server._options.history_depth
        self.client = client
        self.replies = DataWriter(part.participant, part.topic(names.replies), qos=_qos(depth, transient=True))
        loop = server._loop
        self.notifications = DataWriter(
            part.participant, part.topic(names.notifications), qos=_qos(1, transient=True),
            listener=Listener(on_publication_matched=lambda _w, status: post(
                loop, server._notifications_matched, client, status.current_count, status.total_count)),
        )
        self.closed = False

    def close(self) -> None:
        self.closed = True
        _delete(self.notifications)
        _delete(self.replies)


@dataclass(eq=False)
class _Notifier:
    """Notifications of one observation: samples on its client's ``nt`` topic under its token."""

    server: DdsServerTransport
    writers: _ClientWriters
    token: int

    async def notify(self, response: Response, seq: int) -> bool:
        return self.server._write(self.writers, self.writers.notifications, self.token,
                                  self.server._encoded(self.token, response, seq))

    def close(self) -> None:
        if not self.writers.closed:
            with contextlib.suppress(DDSException):
                self.writers.notifications.unregister_instance(Envelope(id=self.token, body=[]))


class DdsServerTransport(ServerCore):
    """Serves a :class:`Service` to the clients that write on its request topic.

    Create with :meth:`start`.  Requests are handled concurrently (at most
    ``options.max_concurrent_requests`` at once).  Samples that are not a
    coapkb request are counted in :attr:`malformed` and dropped."""

    def __init__(self, service: Service, endpoint: Endpoint, participant: _Participant, options: DdsOptions) -> None:
        """Private: use :meth:`start`."""
        super().__init__(service, endpoint, options, log, "dds server")
        self._participant = participant
        self._options = options
        self._loop = asyncio.get_running_loop()
        self._clients: OrderedDict[int, _ClientWriters] = OrderedDict()
        self._draining = False
        names = topic_names(endpoint.host, endpoint.port, 0)
        self._reader = DataReader(
            participant.participant, participant.topic(names.requests), qos=_qos(options.history_depth, transient=False),
            listener=Listener(on_data_available=lambda _r: post(self._loop, self._wake)),
        )
        self._wake()  # anything that arrived before the listener was set

    @classmethod
    async def start(cls, service: Service, endpoint: Endpoint, *, options: DdsOptions | None = None) -> DdsServerTransport:
        """Start a participant on ``endpoint`` and serve.  Port 0 picks a free
        port; the returned transport's :attr:`endpoint` has it.  Raises
        :class:`TransportError` if Cyclone cannot take the port."""
        check_scheme(endpoint, "dds")
        options = options or DdsOptions()
        address = _resolve(endpoint.host)
        if endpoint.port == 0:
            endpoint = Endpoint(endpoint.scheme, endpoint.host, free_port(address))
        try:
            participant = _Participant(server_domain_xml(address, endpoint.port, options.settings))
        except TransportError as exc:
            # Cyclone says only "Non specific error": tell the common cause apart.
            why = f"UDP port {endpoint.port} is already in use" if _port_taken(address, endpoint.port) else str(exc)
            raise TransportError(f"cannot serve on {endpoint}: {why}") from None
        try:
            return cls(service, endpoint, participant, options)
        except BaseException:
            participant.close()
            raise

    # ------------------------------------------------------------------ receiving

    def _wake(self) -> None:
        if not self._draining and not self._closed:
            self._draining = True
            self._spawn(self._drain())

    async def _drain(self) -> None:
        """Take every request waiting; each is served under a concurrency slot."""
        try:
            while not self._closed:
                samples = _take(self._reader)
                if not samples:
                    return
                for client, body in samples:
                    self._count_received(KEY_BYTES + len(body))
                    try:
                        token, request, observe = decode_request(body)
                    except WireError as exc:
                        self._malformed(f"client {client:016x}", str(exc))
                        continue
                    if observe is Observe.DEREGISTER:
                        self._observations.deregister(client, token)
                        continue
                    await self._slots.acquire()
                    self._spawn(self._serve(client, token, request, observe))
        finally:
            self._draining = False

    # ------------------------------------------------------------------ answering

    async def _serve(self, client: int, token: int, request: Request, observe: Observe) -> None:
        try:
            writers = self._writers(client)
            if writers is None:
                return

            async def answer(response: Response, seq: int | None) -> bool:
                return self._write(writers, writers.replies, client, self._encoded(token, response, seq))

            await self._answer(request, answer, sender=None,
                               observe=(client, token) if observe is Observe.REGISTER else None,
                               notifier=lambda gone: _Notifier(self, writers, token))
        finally:
            self._slots.release()

    def _writers(self, client: int) -> _ClientWriters | None:
        """The writers towards ``client``, created on its first request."""
        writers = self._clients.get(client)
        if writers is not None:
            self._clients.move_to_end(client)
            return writers
        if self._closed:
            return None
        try:
            writers = self._clients[client] = _ClientWriters(self, client)
        except DDSException as exc:
            log.warning("dds server %s: cannot create writers for client %016x: %s", self.endpoint, client, exc)
            return None
        while len(self._clients) > self._options.max_clients:
            _, oldest = self._clients.popitem(last=False)
            self._forget(oldest)
        return writers

    def _forget(self, writers: _ClientWriters) -> None:
        self._observations.forget_client(writers.client)
        writers.close()

    def _notifications_matched(self, client: int, current: int, total: int) -> None:
        """The client's notification reader came or went; gone: its observations end."""
        if current == 0 and total > 0 and (writers := self._clients.get(client)) is not None:
            log.debug("dds server %s: client %016x is gone", self.endpoint, client)
            del self._clients[client]
            self._forget(writers)

    def _write(self, writers: _ClientWriters, writer: DataWriter, key_value: int, body: bytes) -> bool:
        if writers.closed or self._closed:
            return False
        try:
            writer.write(Envelope(id=key_value, body=body))
        except DDSException as exc:
            log.warning("dds server %s: write to client %016x failed: %s", self.endpoint, writers.client, exc)
            return False
        self._count_sent(KEY_BYTES + len(body))
        return True

    async def _close_transport(self) -> None:
        """Leave the domain (peers see the participant go at once)."""
        for writers in self._clients.values():
            writers.close()
        self._clients.clear()
        _delete(self._reader)
        self._participant.close()


# =========================================================================== client


class _PeerLink:
    """A client's participant towards one server: its request writer, its
    reply and notification readers, what waits on them."""

    def __init__(self, client: DdsClientTransport, peer: Endpoint) -> None:
        self.peer = peer
        self._client = client
        self._options = client._options
        loop = self._loop = asyncio.get_running_loop()
        address = _resolve(peer.host)
        local = local_address_towards(address, peer.port)
        host = f"[{address}]" if ":" in address else address
        self.participant = _Participant(client_domain_xml(local, f"{host}:{peer.port}", self._options.settings))
        try:
            names = topic_names(peer.host, peer.port, client.id)
            part = self.participant
            depth = self._options.history_depth
            self.matched = asyncio.Event()
            #: Pending requests (and observations' first answers) by token.
            self.waiting: dict[int, asyncio.Future[tuple[Response, int | None]]] = {}
            #: Notification queues of running observations, by token.
            self.observers: dict[int, asyncio.Queue[Delivery | TransportError]] = {}
            self._announcer: asyncio.Task[None] | None = None
            self._discovery_waiters = 0
            self.replies = DataReader(
                part.participant, part.topic(names.replies), qos=_qos(depth, transient=True),
                listener=Listener(on_data_available=lambda _r: post(loop, self._drain_replies)),
            )
            self.notifications = DataReader(
                part.participant, part.topic(names.notifications), qos=_qos(1, transient=True),
                listener=Listener(on_data_available=lambda _r: post(loop, self._drain_notifications)),
            )
            self.requests = DataWriter(
                part.participant, part.topic(names.requests), qos=_qos(depth, transient=False),
                listener=Listener(on_publication_matched=lambda _w, status: post(
                    loop, self._set_matched, status.current_count)),
            )
            self._set_matched(self.requests.get_publication_matched_status().current_count)
        except BaseException:
            self.participant.close()
            raise

    def _set_matched(self, count: int) -> None:
        if count > 0:
            self.matched.set()
        else:
            self.matched.clear()

    async def discovered(self) -> None:
        """Return once the server's request reader is matched, re-announcing
        this participant meanwhile (see the module doc)."""
        if self.matched.is_set():
            return
        self._discovery_waiters += 1
        try:
            if self._announcer is None or self._announcer.done():
                self._announcer = asyncio.ensure_future(self._announce())
            await self.matched.wait()
        finally:
            self._discovery_waiters -= 1

    async def _announce(self) -> None:
        pause = self._options.rediscover_first_s
        while not self.matched.is_set() and self._discovery_waiters > 0:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(pause):
                    await self.matched.wait()
                return
            if self._discovery_waiters > 0:
                self.participant.announce()
            pause = min(pause * 2, self._options.rediscover_max_s)

    def send(self, body: bytes) -> None:
        try:
            self.requests.write(Envelope(id=self._client.id, body=body))
        except DDSException as exc:
            raise TransportError(f"cannot send to {self.peer}: {exc}") from None
        self._client._count_sent(KEY_BYTES + len(body))

    def _decoded(self, samples: list[tuple[int, bytes]]) -> list[tuple[int, Response, int | None]]:
        out = []
        for _, body in samples:
            self._client._count_received(KEY_BYTES + len(body))
            try:
                out.append(decode_response(body))
            except WireError as exc:
                self._client._malformed(self.peer, str(exc))
        return out

    def _drain_replies(self) -> None:
        for token, response, seq in self._decoded(_take(self.replies)):
            waiter = self.waiting.pop(token, None)
            if waiter is not None and not waiter.done():
                waiter.set_result((response, seq))

    def _drain_notifications(self) -> None:
        for token, response, seq in self._decoded(_take(self.notifications)):
            queue = self.observers.get(token)
            if queue is not None:
                put_latest(queue, (response, seq))

    def close(self) -> None:
        if self._announcer is not None:
            self._announcer.cancel()
        for waiter in self.waiting.values():
            if not waiter.done():
                waiter.set_exception(TransportError("the dds client transport was closed"))
        self.waiting.clear()
        self.participant.close()


class DdsClientTransport(ClientCore):
    """Sends requests to robots serving over DDS; one participant per peer, opened on first use."""

    def __init__(self, *, options: DdsOptions | None = None) -> None:
        self._options = options or DdsOptions()
        super().__init__(self._options, log, "dds client")
        #: This client's key on every server's request topic and the suffix of its reply topics.
        self.id = int.from_bytes(os.urandom(8), "big")
        self._links: dict[Endpoint, _PeerLink] = {}
        self._tokens = itertools.count(int.from_bytes(os.urandom(4), "big"))

    def _link(self, peer: Endpoint) -> _PeerLink:
        self._check_open()
        check_scheme(peer, "dds")
        link = self._links.get(peer)
        if link is None:
            try:
                link = self._links[peer] = _PeerLink(self, peer)
            except OSError as exc:  # no route to the peer's address
                raise PeerUnreachable(f"cannot reach {peer}: {exc}") from None
        return link

    async def _exchange(self, link: _PeerLink, request: Request, token: int, observe: Observe | bool,
                        timeout: float) -> tuple[Response, int | None]:
        """One request and its reply within ``timeout`` (discovery included)."""
        loop = asyncio.get_running_loop()
        body = encode_request(request, token=token, observe=observe)
        reply: asyncio.Future[tuple[Response, int | None]] = loop.create_future()
        link.waiting[token] = reply
        stage = "discovered"
        try:
            async with asyncio.timeout(timeout):
                await link.discovered()
                stage = "answered"
                link.send(body)
                return await reply
        except TimeoutError:
            if stage == "discovered":
                raise PeerUnreachable(f"no DDS participant discovered at {link.peer} within {timeout:g}s") from None
            raise PeerTimeout(f"no answer from {link.peer} within {timeout:g}s") from None
        finally:
            link.waiting.pop(token, None)

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        """Send ``request`` to ``peer`` and return its answer.

        Raises :class:`PeerUnreachable` when no participant is discovered at
        ``peer`` or no answer arrives within ``timeout`` seconds, and
        :class:`TransportError` for other failures (transport closed)."""
        link = self._link(peer)
        response, _ = await self._exchange(link, request, next(self._tokens) % 2**64, False, timeout)
        return response

    async def observe(
        self, peer: Endpoint, request: Request, *, timeout: float | None = None
    ) -> AsyncIterator[Response]:
        """The current representation, then one item per change.

        ``timeout`` (default ``options.observe_timeout_s``) bounds the wait
        for the first answer (:class:`PeerUnreachable`).  The iteration ends
        after the first item if the server did not register the observation,
        and after an error notification.  Closing the iterator deregisters.
        If the peer dies the iterator just stops yielding, as with ZeroMQ."""
        timeout = self._options.observe_timeout_s if timeout is None else timeout
        link = self._link(peer)
        token = next(self._tokens) % 2**64
        queue: asyncio.Queue[Delivery | TransportError] = asyncio.Queue(maxsize=self._options.observe_queue)
        link.observers[token] = queue
        state: ObserverState | None = None
        try:
            with self._observation(queue):
                response, seq = await self._exchange(link, request, token, Observe.REGISTER, timeout)
                state = ObserverState(response, seq)
                yield response
                while state.registered:
                    response, seq = state.delivered(await queue.get())
                    # A notification that arrived before the registration's answer is stale.
                    if state.accept(response, seq):
                        yield response
        finally:
            link.observers.pop(token, None)
            if state is not None and state.registered and not self._closed and link is self._links.get(peer):
                with contextlib.suppress(TransportError, ValueError):
                    link.send(encode_request(Request(request.method, request.path), token=token,
                                             observe=Observe.DEREGISTER))

    async def aclose(self) -> None:
        """Leave every peer's domain (pending requests fail with :class:`TransportError`).  Idempotent."""
        if self._closed:
            return
        self._closed = True
        links, self._links = list(self._links.values()), {}
        for link in links:
            link.close()
        self._end_observations()
