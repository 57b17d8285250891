"""The CoAP server of a robot: a :class:`~coapkb.transport.base.Service` over UDP.

Every :class:`ResourceInfo` of the service becomes an aiocoap resource,
plus ``/.well-known/core`` (RFC 6690).  Block-wise transfer (RFC 7959,
:mod:`.blockwise`), Observe (RFC 7641) and FETCH (RFC 8132) come from
aiocoap.  ``SO_REUSEPORT`` would let a second server silently share a port:
binding checks the port first and fails clearly.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import ipaddress
import logging
import socket
from dataclasses import replace
from typing import Any

import aiocoap
import aiocoap.resource

from ..base import Endpoint, RateLimitFilter, ResourceInfo, Service, TrafficCounters, TransportError, handle_safely
from ..messages import Response, Status
from ..observation import refresh_after
from .aiocoap_adapter import ContextHooks, local_port
from .blockwise import BodyAwareBlock2Cache, GapSafeBlock1Spool
from .bounds import StateBounds
from .heap import trim_heap
from .mapping import BODY_HASH_PARAM, body_hash, message_from_response, request_from_message
from .reliability import ReliabilityLayer, make_reliability
from .reliability.notifications import NotificationPolicy, NotificationTypes
from .security import CoapServerSecurity

log = logging.getLogger(__name__)



class _ServiceResource(aiocoap.resource.ObservableResource):
    """One path of a :class:`Service` as an aiocoap resource."""

    def __init__(self, service: Service, info: ResourceInfo, tuning_for: Any,
                 security: CoapServerSecurity | None,
                 blocks: tuple[GapSafeBlock1Spool, BodyAwareBlock2Cache], observers: int) -> None:
        super().__init__()
        #: Observations this resource keeps (:class:`.StateBounds`).
        self._observers_max = observers
        #: Tells who sent a request (OSCORE/EDHOC), or None (unprotected).
        self._security = security
        # One spool and one cache per server (block keys name the path), so
        # their bounds are the server's, not multiplied by its resources.
        self._block1, self._block2 = blocks
        self.service = service
        self.info = info
        self._tuning_for = tuning_for
        self.rt = info.rt
        #: For a ``quiet`` resource: each observation's request and the
        #: last answer it was sent (code, content-format, payload).
        self._watched: dict[Any, aiocoap.Message] = {}
        self._sent: dict[Any, tuple[object, ...]] = {}
        #: Each observation's timer for the refresh of its answer before
        #: that answer's Max-Age runs out, and those whose timer went off.
        self._refresh_timers: dict[Any, asyncio.TimerHandle] = {}
        self._stale: set[Any] = set()
        self._dirty = False
        self._refresher: asyncio.Task[None] | None = None
        if info.obs:
            service.subscribe(info.path, self.updated_state)

    def get_link_description(self) -> dict[str, Any]:
        link: dict[str, Any] = {}
        if self.info.rt:
            link["rt"] = self.info.rt
        if self.info.ct:
            link["ct"] = " ".join(str(int(c)) for c in self.info.ct)
        if self.info.title:
            link["title"] = self.info.title
        if self.info.obs:
            link["obs"] = None
        return link

    async def render(self, request: aiocoap.Message) -> aiocoap.Message:
        sender = None if self._security is None else self._security.sender(request)
        refused = self.service.admit(sender, request.code.name, self.info.path)
        if refused is not None:  # before anything else: a refused request changes nothing
            return message_from_response(refused)
        try:
            req = request_from_message(self.info.path, request)
        except ValueError:
            return message_from_response(Response.error(Status.METHOD_NOT_ALLOWED, f"{request.code} not supported"))
        req = replace(req, peer=sender)  # who, for a service that cares (the RD, the lease)
        sent_hash = dict(q.partition("=")[::2] for q in request.opt.uri_query).get(BODY_HASH_PARAM)
        if req.payload and sent_hash is not None and sent_hash != body_hash(req.payload):
            return message_from_response(Response.error(Status.BAD_REQUEST, f"{BODY_HASH_PARAM} does not match body"))
        response = await handle_safely(self.service, req, log)
        message = message_from_response(response)
        # Piggybacked answers are never retransmitted; CON notifications
        # follow the notification policy's timers.
        message.transport_tuning = self._tuning_for(request, response.confirm)
        for observation, watched in self._watched.items():
            if watched is request and observation not in self._sent:  # an observation's first answer
                self._sent[observation] = _digest(message)
                self._keep_fresh(observation, message)
        return message

    async def add_observation(self, request: aiocoap.Message, serverobservation: Any) -> None:
        if self.info.obs and len(self._observations) < self._observers_max:
            await super().add_observation(request, serverobservation)
            if self.info.quiet:
                self._watched[serverobservation] = request

    def updated_state(self, response: Any = None) -> None:
        """A change: every observer is notified, or, for a ``quiet``
        resource (a query), only those whose answer it changed."""
        if not self.info.quiet:
            super().updated_state(response)
            return
        self._dirty = True
        self._start_refresher()

    def _start_refresher(self) -> None:
        if self._refresher is None or self._refresher.done():
            self._refresher = asyncio.ensure_future(self._refresh())

    def _keep_fresh(self, observation: Any, message: aiocoap.Message) -> None:
        """Send ``observation`` its answer again shortly before the Max-Age
        of ``message`` (just sent to it) runs out, unless a change does first:
        its client's copy stays fresh, and a client that hears nothing for
        longer knows the observation is lost (a restarted server's is).
        Only a quiet resource keeps each observation's request to answer it
        with; the others carry no Max-Age."""
        if (timer := self._refresh_timers.pop(observation, None)) is not None:
            timer.cancel()
        after = refresh_after(message.opt.max_age) if message.code.is_successful() else None
        if after is not None:
            self._refresh_timers[observation] = asyncio.get_running_loop().call_later(
                after, self._refresh_due, observation)

    def _refresh_due(self, observation: Any) -> None:
        self._refresh_timers.pop(observation, None)
        self._stale.add(observation)
        self._start_refresher()

    def close(self) -> None:
        """Stop the refresh timers (the server is closing)."""
        for timer in self._refresh_timers.values():
            timer.cancel()
        self._refresh_timers.clear()
        self._stale.clear()

    async def _refresh(self) -> None:
        # Changes while answers are computed are coalesced into one more pass.
        while self._dirty or self._stale:
            changed, self._dirty = self._dirty, False
            stale, self._stale = self._stale, set()
            for observation, request in list(self._watched.items()):
                if observation not in self._observations:  # cancelled
                    self._watched.pop(observation, None)
                    self._sent.pop(observation, None)
                    if (timer := self._refresh_timers.pop(observation, None)) is not None:
                        timer.cancel()
                    continue
                if not changed and observation not in stale:
                    continue
                message = await self.render(request)
                digest = _digest(message)
                if self._sent.get(observation) != digest or observation in stale:
                    self._sent[observation] = digest
                    self._keep_fresh(observation, message)
                    observation.trigger(message)


def _digest(message: aiocoap.Message) -> tuple[object, ...]:
    return (message.code, message.opt.content_format, message.payload)


class _UnknownPaths(aiocoap.resource.Resource, aiocoap.resource.PathCapable):
    """The paths under ``parent`` that no resource has.  The service answers
    them, so its 4.04 says what exists there (the named queries beside a
    misspelled one); aiocoap's own 4.04 carries no diagnostic."""

    def __init__(self, service: Service, parent: str) -> None:
        super().__init__()
        self.service = service
        self.parent = parent

    async def render(self, request: aiocoap.Message) -> aiocoap.Message:
        path = self.parent + "/" + "/".join(request.opt.uri_path)
        try:
            req = request_from_message(path, request)
        except ValueError:
            return message_from_response(Response.error(Status.METHOD_NOT_ALLOWED, f"{request.code} not supported"))
        return message_from_response(await handle_safely(self.service, req, log))


def _check_port_free(host: str, port: int) -> None:
    """Fail clearly if another process already serves CoAP on (host, port).

    aiocoap binds with SO_REUSEPORT, which would let a second server share the
    port silently and steal its traffic; this probe binds without it."""
    if port == 0:
        return
    addr = ipaddress.ip_address(host)
    bind_host = f"::ffff:{addr}" if addr.version == 4 else host
    probe = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM)
    try:
        probe.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 0)
        probe.bind((bind_host, port))
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            raise TransportError(f"UDP port {host}:{port} is already in use by another server") from None
        raise TransportError(f"cannot bind {host}:{port}: {exc.strerror}") from None
    finally:
        probe.close()


def _resolve_host(host: str) -> str:
    try:
        ipaddress.ip_address(host)
        return host
    except ValueError:
        try:
            return str(socket.getaddrinfo(host, None, type=socket.SOCK_DGRAM)[0][4][0])
        except socket.gaierror as exc:
            raise TransportError(f"cannot resolve {host!r}: {exc.strerror}") from None


class CoapServerTransport:
    """Serves a :class:`Service` over CoAP/UDP.

    ``reliability`` times the server's confirmable messages (Observe
    notifications): a :class:`ReliabilityLayer` shared with the robot's
    client (its path estimates), or None for one of its own."""

    def __init__(self, ctx: aiocoap.Context, endpoint: Endpoint, hooks: ContextHooks, policy: NotificationPolicy,
                 blocks: tuple[GapSafeBlock1Spool, BodyAwareBlock2Cache],
                 bounds: StateBounds, security: CoapServerSecurity | None = None,
                 resources: tuple[_ServiceResource, ...] = ()) -> None:
        self._ctx = ctx
        self._resources = resources
        self.bounds = bounds
        self._hooks = hooks
        self.endpoint = endpoint
        self.counters: TrafficCounters = hooks.counters
        self.policy = policy
        self.blocks = blocks
        self._security = security
        self._sweeper = asyncio.create_task(self._sweep(), name=f"coap state sweep {endpoint.hostport}")

    async def _sweep(self) -> None:
        while True:
            await asyncio.sleep(self.bounds.sweep_every_s)  # a period, not a wait for an event
            dropped = self._hooks.forget_duplicates()
            for state in self.blocks:
                dropped += state.purge()
            if self._security is not None:
                self._security.sweep()
            if dropped >= self.bounds.trim_after_bytes:
                trim_heap()

    @classmethod
    async def start(
        cls, service: Service, endpoint: Endpoint,
        reliability: ReliabilityLayer | None = None,
        security: CoapServerSecurity | None = None,
        bounds: StateBounds | None = None,
    ) -> CoapServerTransport:
        """``security``: OSCORE + EDHOC (:mod:`coapkb.security.coap`) on every
        resource but ``/.well-known/core``, or None; ``service`` carries the
        access rules (:meth:`Service.admit`).  ``bounds``: how much state the
        server keeps (default :class:`.StateBounds`'s)."""
        bounds = bounds or StateBounds()
        host = _resolve_host(endpoint.host)
        _check_port_free(host, endpoint.port)
        layer = make_reliability() if reliability is None else reliability
        policy = NotificationPolicy(layer)
        # An answer to a NON try is NON (the client's layer repeats the try
        # if it is lost); notifications as NotificationTypes says.
        tuning_for = NotificationTypes(layer.settings.confirm_every).tuning_for
        site = aiocoap.resource.Site()
        site.add_resource(
            [".well-known", "core"],
            aiocoap.resource.WKCResource(site.get_resources_as_linkheader, impl_info=None),
        )
        parents: set[tuple[str, ...]] = set()
        blocks = (GapSafeBlock1Spool(bounds), BodyAwareBlock2Cache(bounds=bounds))
        resources = []
        for info in service.resources():
            segments = [s for s in info.path.split("/") if s]
            resources.append(_ServiceResource(service, info, tuning_for, security, blocks, bounds.observers))
            site.add_resource(segments, resources[-1])
            parents.add(tuple(segments[:-1]))
        for parent in sorted(parents - {()}):
            site.add_resource(list(parent), _UnknownPaths(service, "/" + "/".join(parent)))
        logger = logging.getLogger("coapkb.coap.server")
        RateLimitFilter.install(logger)
        try:
            ctx = await aiocoap.Context.create_server_context(
                site if security is None else security.wrap(site), bind=(host, endpoint.port), transports=["udp6"],
                loggername=logger.name, server_credentials=None if security is None else security.credentials,
            )
        except OSError as exc:
            raise TransportError(f"cannot serve CoAP on {endpoint.hostport}: {exc.strerror or exc}") from None
        hooks = ContextHooks.of(ctx, bounds)
        hooks.set_con_policy(policy)
        hooks.on_datagram = layer.on_datagram
        return cls(ctx, Endpoint("coap", endpoint.host, local_port(ctx)), hooks, policy, blocks, bounds, security,
                   tuple(resources))

    def describe(self) -> dict[str, Any]:
        return {"profile": {"name": ReliabilityLayer.name}, "notifications": "timed from the client's path estimates"}

    async def aclose(self) -> None:
        self._sweeper.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._sweeper
        self._hooks.cancel_empty_ack_timers()
        for resource in self._resources:
            resource.close()
        await self._ctx.shutdown()
        self._hooks.remove()
