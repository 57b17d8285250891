"""An in-process transport for unit tests: no sockets, no processes, no wire.

:class:`MemoryNetwork` stands for the network: servers register their
:class:`~coapkb.transport.base.Service` under an :class:`Endpoint`, clients
call it directly.  It implements the one transport interface of
:mod:`coapkb.transport.base` (request/response and Observe) with the
semantics the agent relies on -- a request to an unknown or closed peer, or
one that does not complete within its ``timeout``, raises
:class:`PeerUnreachable`; an observation yields the current representation,
then one per change, and ends with :class:`PeerUnreachable` when the server
closes -- so the agent's modules can be tested without a team of processes.

It is not a third transport of the system: nothing is encoded, nothing is
lost or reordered, and the byte counters count payloads only.  Retransmission,
Block-wise transfer and the wire formats are tested on the real transports.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable

from .base import Endpoint, PeerGone, PeerTimeout, PeerUnreachable, Service, TrafficCounters
from .messages import Request, Response


class MemoryNetwork:
    """Which :class:`MemoryServerTransport` listens on which endpoint."""

    def __init__(self) -> None:
        self._servers: dict[Endpoint, MemoryServerTransport] = {}

    async def serve(self, service: Service, endpoint: Endpoint) -> MemoryServerTransport:
        """Expose ``service`` on ``endpoint`` (the endpoint must be free)."""
        if endpoint in self._servers:
            raise OSError(f"{endpoint} is already in use")
        server = MemoryServerTransport(self, service, endpoint)
        self._servers[endpoint] = server
        return server

    def client(self) -> MemoryClientTransport:
        return MemoryClientTransport(self)

    def server_at(self, peer: Endpoint) -> MemoryServerTransport:
        server = self._servers.get(peer)
        if server is None:
            raise PeerGone(f"{peer}: nobody listens there")
        return server

    def _remove(self, server: MemoryServerTransport) -> None:
        if self._servers.get(server.endpoint) is server:
            del self._servers[server.endpoint]


class MemoryServerTransport:
    """A service reachable through a :class:`MemoryNetwork` until :meth:`aclose`."""

    def __init__(self, network: MemoryNetwork, service: Service, endpoint: Endpoint) -> None:
        self.network = network
        self.service = service
        self.endpoint = endpoint
        self.counters = TrafficCounters()
        self._on_close: set[Callable[[], None]] = set()

    async def handle(self, request: Request) -> Response:
        self.counters.messages_received += 1
        self.counters.bytes_received += len(request.payload)
        response = await self.service.handle(request)
        self.counters.messages_sent += 1
        self.counters.bytes_sent += len(response.payload)
        return response

    def when_closed(self, callback: Callable[[], None]) -> Callable[[], None]:
        """Call ``callback`` on :meth:`aclose`; returns a function that cancels it."""
        self._on_close.add(callback)
        return lambda: self._on_close.discard(callback)

    async def aclose(self) -> None:
        self.network._remove(self)
        for callback in list(self._on_close):
            callback()
        self._on_close.clear()


class MemoryClientTransport:
    """The client side of a :class:`MemoryNetwork`."""

    def __init__(self, network: MemoryNetwork) -> None:
        self.network = network
        self.counters = TrafficCounters()
        self._closed = False

    def _server(self, peer: Endpoint) -> MemoryServerTransport:
        if self._closed:
            raise PeerUnreachable(f"{peer}: this client is closed")
        return self.network.server_at(peer)

    async def _exchange(self, server: MemoryServerTransport, request: Request) -> Response:
        self.counters.messages_sent += 1
        self.counters.bytes_sent += len(request.payload)
        response = await server.handle(request)
        self.counters.messages_received += 1
        self.counters.bytes_received += len(response.payload)
        return response

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        """Send ``request``; :class:`PeerUnreachable` if nobody listens at ``peer``,
        or the service has not answered within ``timeout`` seconds."""
        server = self._server(peer)
        try:
            async with asyncio.timeout(timeout):
                return await self._exchange(server, request)
        except TimeoutError:
            raise PeerTimeout(f"{peer}: no answer within {timeout:g}s") from None

    async def observe(self, peer: Endpoint, request: Request) -> AsyncIterator[Response]:
        """The current representation of ``request.path``, then one per change
        the service announces; ends with :class:`PeerUnreachable` when the server closes."""
        server = self._server(peer)
        changed = asyncio.Event()
        closed = asyncio.Event()
        unsubscribe = server.service.subscribe(request.path, changed.set)

        def on_close() -> None:
            closed.set()
            changed.set()

        forget = server.when_closed(on_close)
        try:
            while True:
                changed.clear()
                yield await self._exchange(server, request)
                await changed.wait()
                if closed.is_set() or self._closed:
                    raise PeerUnreachable(f"{peer}: the server closed; observation of {request.path} ended")
        finally:
            unsubscribe()
            forget()

    async def aclose(self) -> None:
        self._closed = True
