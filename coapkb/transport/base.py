"""The one transport interface.

A transport moves :class:`~coapkb.transport.messages.Request` / ``Response`` pairs
between robots.  The client side is :class:`ClientTransport`; the server side
exposes a :class:`Service` (the robot's resources) through a
:class:`ServerTransport`.  CoAP/UDP (``coap``), ZeroMQ/TCP (``zmq``),
Zenoh (``zenoh``, ``zenoh+udp``, ``zenoh+quic``) and DDS (``dds``) implement both; the agent, CLI and
benchmarks only see these protocols.
"""

from __future__ import annotations

import abc
import asyncio
import logging
import socket
from collections.abc import AsyncIterator, Callable, Mapping
from dataclasses import dataclass, fields
from typing import Protocol

from .. import clock
from ..errors import CoapkbError
from .messages import Request, Response, Status


class RateLimiter:
    """At most one event per ``interval_s``; counts the ones it swallowed.

    Servers log malformed input through this, so a peer spraying garbage
    cannot flood the log (or the disk)."""

    def __init__(self, interval_s: float = 10.0) -> None:
        self.interval_s = interval_s
        self._last = -float("inf")
        self._suppressed = 0

    def allow(self) -> int | None:
        """None if the event must be dropped; else how many were dropped since the last one."""
        now = clock.monotonic()
        if now - self._last < self.interval_s:
            self._suppressed += 1
            return None
        self._last, suppressed, self._suppressed = now, self._suppressed, 0
        return suppressed


class RateLimitFilter(logging.Filter):
    """One :class:`RateLimiter` per message template, so a stream of garbage
    datagrams (each logged by aiocoap) cannot flood the log.

    Errors pass, unless ``peer_errors``: a logger whose errors are about what
    a peer sent (a security layer refusing a stranger's message) has them
    rate-limited too, and reported as warnings: they are not the robot's."""

    def __init__(self, interval_s: float = 10.0, peer_errors: bool = False) -> None:
        super().__init__()
        self.interval_s = interval_s
        self.peer_errors = peer_errors
        self._limiters: dict[str, RateLimiter] = {}

    @classmethod
    def install(cls, logger: logging.Logger, peer_errors: bool = False) -> None:
        """Add one to ``logger`` unless it has one."""
        if not any(isinstance(f, cls) for f in logger.filters):
            logger.addFilter(cls(peer_errors=peer_errors))

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.ERROR:
            if not self.peer_errors or record.exc_info:
                return True
            record.levelno, record.levelname = logging.WARNING, "WARNING"
        key = str(record.msg)
        suppressed = self._limiters.setdefault(key, RateLimiter(self.interval_s)).allow()
        if suppressed is None:
            return False
        if suppressed:
            record.msg = f"{record.msg} (and {suppressed} similar messages suppressed)"
        return True


class RateLimitedLog:
    """Warnings through a :class:`RateLimiter`, saying how many were swallowed."""

    def __init__(self, logger: logging.Logger, interval_s: float) -> None:
        self._logger = logger
        self._limiter = RateLimiter(interval_s)

    def warning(self, msg: str, *args: object) -> None:
        suppressed = self._limiter.allow()
        if suppressed is None:
            return
        if suppressed:
            msg += " (%d similar warnings suppressed)"
            args = (*args, suppressed)
        self._logger.warning(msg, *args)


class TransportError(CoapkbError):
    """A request could not be completed: peer unreachable, timed out, or reset."""


class PeerUnreachable(TransportError):
    """No answer from the peer within the time budget (after retransmissions)."""


class PeerGone(PeerUnreachable):
    """The network reported that nobody listens at the peer's address (ICMP
    port unreachable): its process is not there, whatever the timing."""


class PeerTimeout(PeerUnreachable):
    """The time budget ran out with no answer (not an error the network
    reported, such as ICMP's port unreachable): the silence may be this
    process's own, if its loop ran late (local health)."""


@dataclass(frozen=True)
class Endpoint:
    """Where a robot listens: ``scheme://host:port`` (a scheme of :mod:`.registry`,
    which parses one: :func:`~.registry.parse_endpoint`)."""

    scheme: str
    host: str
    port: int

    @property
    def hostport(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{host}:{self.port}"

    def __str__(self) -> str:
        return f"{self.scheme}://{self.hostport}"


@dataclass
class TrafficCounters:
    """What one process put on and took off its sockets (payload of UDP datagrams or
    TCP segments as seen by the application; IP/UDP/TCP headers are not included).
    Retransmissions count as sent again."""

    bytes_sent: int = 0
    bytes_received: int = 0
    messages_sent: int = 0
    messages_received: int = 0
    retransmissions: int = 0
    #: Observe notifications among the messages sent (first transmissions;
    #: a CON one sent again counts under ``retransmissions``).
    notifications_sent: int = 0

    def as_dict(self) -> dict[str, int]:
        return dict(vars(self))

    @classmethod
    def from_dict(cls, data: Mapping[str, int]) -> TrafficCounters:
        """The inverse of :meth:`as_dict`; a counter missing from ``data`` is 0
        (a record written before that counter existed)."""
        return cls(**{f.name: int(data.get(f.name, 0)) for f in fields(cls)})

    def __add__(self, other: TrafficCounters) -> TrafficCounters:
        return TrafficCounters(*(getattr(self, f.name) + getattr(other, f.name) for f in fields(self)))


@dataclass(frozen=True)
class ResourceInfo:
    """A resource as advertised in discovery (RFC 6690 attributes)."""

    path: str
    rt: str | None = None
    ct: tuple[int, ...] = ()
    obs: bool = False
    title: str | None = None
    methods: tuple[str, ...] = ("GET",)
    #: Observers are notified only when their answer changed (a query's
    #: answer is the same after most changes of the KB), not at every change.
    quiet: bool = False


class Service(abc.ABC):
    """A robot's resources, independent of transport."""

    @abc.abstractmethod
    def resources(self) -> list[ResourceInfo]:
        """All resources, for discovery and routing."""

    @abc.abstractmethod
    async def handle(self, request: Request) -> Response:
        """Answer one request.  Must not raise: errors become 4.xx/5.xx responses."""

    def subscribe(self, path: str, on_change: Callable[[], None]) -> Callable[[], None]:
        """Call ``on_change`` whenever the resource at ``path`` changes (for Observe).
        Returns a function that cancels the subscription.  Default: never changes."""
        return lambda: None

    def admit(self, sender: str | None, method: str, path: str) -> Response | None:
        """The answer refusing ``method`` on ``path`` to ``sender`` (the team
        member the transport's security authenticated, None if none), or None
        to serve it.  Every transport asks before anything else, so a refused
        request changes nothing.  Default: everything is served (access rules
        come from :class:`~coapkb.transport.security.GuardedService`)."""
        return None


async def handle_safely(service: Service, request: Request, log: logging.Logger) -> Response:
    """``service.handle(request)`` that cannot take a server down: an exception
    or a non-Response is logged on ``log`` and answered 5.00."""
    try:
        response = await service.handle(request)
    except asyncio.CancelledError:
        raise
    except Exception:
        log.exception("Service.handle raised on %s %s (it must answer 5.xx instead)", request.method, request.path)
        return Response.error(Status.INTERNAL_SERVER_ERROR, "internal error")
    if not isinstance(response, Response):
        log.error("Service.handle returned %r for %s %s, not a Response", response, request.method, request.path)
        return Response.error(Status.INTERNAL_SERVER_ERROR, "internal error")
    return response


class ClientTransport(Protocol):
    """The client side: send a request to a peer, get its response."""

    counters: TrafficCounters

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        """Send ``request``; raise :class:`PeerUnreachable` if ``timeout`` passes."""
        ...

    def observe(self, peer: Endpoint, request: Request) -> AsyncIterator[Response]:
        """The current representation of a resource, then one item per change."""
        ...

    async def aclose(self) -> None: ...


class ServerTransport(Protocol):
    """The server side: expose a :class:`Service` on an endpoint."""

    counters: TrafficCounters
    endpoint: Endpoint

    async def aclose(self) -> None: ...


def free_port(host: str, kind: int = socket.SOCK_DGRAM) -> int:
    """A port free right now on ``host``, for a library that cannot say which
    port it took for ``:0`` (Zenoh, Cyclone DDS).  Another process may take it
    before the caller binds it: callers that can should pass real ports."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, kind) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])
