"""CoAP over UDP (RFC 7252) with aiocoap: the primary transport.

Server: every :class:`ResourceInfo` of a :class:`Service` becomes an aiocoap
resource, plus ``/.well-known/core`` (RFC 6690).  Block-wise transfer (RFC
7959), Observe (RFC 7641) and FETCH (RFC 8132) come from aiocoap; two of its
pitfalls are handled here:

* its Block2 cache keys on the request options but not the body, so two
  concurrent FETCHes with different queries could get each other's blocks.
  The server keys its cache on the body too, and the client puts a hash of
  the body in the URI (``qh=``) so that even the body-less follow-up block
  requests aiocoap sends are unambiguous.
* ``SO_REUSEPORT`` lets a second server silently share a port: binding
  checks the port first and fails clearly.
"""

from __future__ import annotations

import asyncio
import errno
import hashlib
import ipaddress
import logging
import socket
from collections import OrderedDict
from typing import Any, AsyncIterator, Callable

import aiocoap
import aiocoap.error
import aiocoap.resource
from aiocoap.blockwise import Block1Spool, Block2Cache, IncompleteException, _extract_block_key
from aiocoap.numbers.codes import Code
from aiocoap.numbers.constants import TransportTuning
from aiocoap.optiontypes import BlockOption
from aiocoap.util.asyncio.timeoutdict import TimeoutDict

from .reliability.cocoa_hooks import RetransmissionController
from ..messages import Method, Request, Response, Status
from .reliability.rto import TransmissionProfile
from ..base import (
    Endpoint,
    PeerUnreachable,
    RateLimiter,
    ResourceInfo,
    Service,
    TrafficCounters,
    TransportError,
)

#: URI-Query parameter carrying a hash of the request body (see module doc).
BODY_HASH_PARAM = "qh"

_METHOD_CODES = {m: getattr(Code, m.value) for m in Method}

log = logging.getLogger(__name__)


def body_hash(payload: bytes) -> str:
    return hashlib.blake2s(payload, digest_size=6).hexdigest()


def status_to_code(status: Status) -> Code:
    return Code((status // 100) << 5 | status % 100)


def code_to_status(code: Code) -> Status:
    try:
        return Status(code.class_ * 100 + (int(code) & 0x1F))
    except ValueError:
        raise TransportError(f"unexpected CoAP response code {code.dotted}") from None


# --------------------------------------------------------------------------- server


class _RateLimitFilter(logging.Filter):
    """One :class:`RateLimiter` per message template, so a stream of garbage
    datagrams (each logged by aiocoap) cannot flood the log.  Errors pass."""

    def __init__(self, interval_s: float = 10.0) -> None:
        super().__init__()
        self.interval_s = interval_s
        self._limiters: dict[str, RateLimiter] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.ERROR:
            return True
        key = str(record.msg)
        suppressed = self._limiters.setdefault(key, RateLimiter(self.interval_s)).allow()
        if suppressed is None:
            return False
        if suppressed:
            record.msg = f"{record.msg} (and {suppressed} similar messages suppressed)"
        return True


class _GapSafeBlock1Spool(Block1Spool):
    """aiocoap's Block1 spool answers a gap in the blocks (ValueError) with a
    5.00 and a logged traceback; it is the client's error: 4.08 Incomplete."""

    def feed_and_take(self, req: aiocoap.Message) -> aiocoap.Message:
        try:
            return super().feed_and_take(req)
        except ValueError:
            raise IncompleteException from None


class _BodyAwareBlock2Cache(Block2Cache):
    """aiocoap's Block2 cache, keyed on the request body as well.

    Follow-up block requests without a body (as aiocoap's client sends them)
    are served only when exactly one cached answer matches; otherwise 4.08,
    so an answer never reaches the wrong query."""

    def __init__(self) -> None:
        super().__init__()
        lifetime = TransportTuning().MAX_TRANSMIT_WAIT
        self._completes = TimeoutDict(lifetime)
        self._bodies: TimeoutDict = TimeoutDict(lifetime)

    async def extract_or_insert(self, req: aiocoap.Message, response_builder: Callable[[], Any]) -> aiocoap.Message:
        base_key = _extract_block_key(req)
        body = hashlib.blake2s(req.payload, digest_size=8).digest() if req.payload else None
        if req.opt.block2 is None or req.opt.block2.block_number == 0:
            assembled = await response_builder()
            if body is None:
                body = b""
        else:
            if body is None:
                try:
                    candidates = self._bodies[base_key]
                except KeyError:
                    raise IncompleteException from None
                if len(candidates) != 1:
                    raise IncompleteException
                (body,) = candidates
            try:
                assembled = self._completes[(base_key, body)]
            except KeyError:
                raise IncompleteException from None
        too_big = len(assembled.payload) > req.remote.maximum_payload_size or (
            req.opt.block2 is not None and len(assembled.payload) > req.opt.block2.size
        )
        if not too_big:
            return assembled
        self._completes[(base_key, body)] = assembled
        try:
            bodies = self._bodies[base_key]
        except KeyError:
            bodies = set()
        bodies.add(body)
        self._bodies[base_key] = bodies
        block2 = req.opt.block2 or BlockOption.BlockwiseTuple(0, 0, req.remote.maximum_block_size_exp)
        return assembled._extract_block(block2.block_number, block2.size_exponent, req.remote.maximum_payload_size)


def _request_from_message(path: str, msg: aiocoap.Message) -> Request:
    query: dict[str, str] = {}
    for item in msg.opt.uri_query:
        key, _, value = item.partition("=")
        if key != BODY_HASH_PARAM:  # transport-level; the service never sees it
            query[key] = value
    return Request(
        method=Method(str(msg.code)),
        path=path,
        query=query,
        payload=msg.payload,
        content_format=None if msg.opt.content_format is None else int(msg.opt.content_format),
        accept=None if msg.opt.accept is None else int(msg.opt.accept),
        etags=tuple(msg.opt.etags),
    )


def _message_from_response(response: Response) -> aiocoap.Message:
    msg = aiocoap.Message(code=status_to_code(response.status), payload=response.payload)
    if response.content_format is not None:
        msg.opt.content_format = response.content_format
    if response.max_age is not None:
        msg.opt.max_age = response.max_age
    if response.etag is not None:
        msg.opt.etag = response.etag
    return msg


class _ServiceResource(aiocoap.resource.ObservableResource):
    """One path of a :class:`Service` as an aiocoap resource."""

    def __init__(self, service: Service, info: ResourceInfo, retransmission: RetransmissionController) -> None:
        super().__init__()
        self._block1 = _GapSafeBlock1Spool()
        self._block2 = _BodyAwareBlock2Cache()
        self.service = service
        self.info = info
        self.retransmission = retransmission
        self.rt = info.rt
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
        try:
            req = _request_from_message(self.info.path, request)
        except ValueError:
            return _message_from_response(Response.error(Status.METHOD_NOT_ALLOWED, f"{request.code} not supported"))
        sent_hash = dict(q.partition("=")[::2] for q in request.opt.uri_query).get(BODY_HASH_PARAM)
        if req.payload and sent_hash is not None and sent_hash != body_hash(req.payload):
            return _message_from_response(Response.error(Status.BAD_REQUEST, f"{BODY_HASH_PARAM} does not match body"))
        try:
            response = await self.service.handle(req)
        except Exception:  # the service must not raise; never let a bug kill the server
            log.exception("service failed on %s", self.info.path)
            response = Response.error(Status.INTERNAL_SERVER_ERROR, "internal error")
        message = _message_from_response(response)
        # Piggybacked answers are never retransmitted, but Observe notifications
        # are CON: give them this peer's timeouts rather than RFC 7252's 2-3 s.
        message.transport_tuning = self.retransmission.tuning_for(request.remote.hostinfo, reliability=None)
        return message

    async def add_observation(self, request: aiocoap.Message, serverobservation: Any) -> None:
        if self.info.obs:
            await super().add_observation(request, serverobservation)


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
            return socket.getaddrinfo(host, None, type=socket.SOCK_DGRAM)[0][4][0]
        except socket.gaierror as exc:
            raise TransportError(f"cannot resolve {host!r}: {exc.strerror}") from None


def _udp_interface(ctx: aiocoap.Context) -> Any:
    """The UDP message interface of a context created with transports=['udp6']."""
    return ctx.request_interfaces[0].token_interface.message_interface


def _count_traffic(ctx: aiocoap.Context, counters: TrafficCounters) -> None:
    """Count datagrams at this context's socket (retransmissions included).

    aiocoap has no counters, so the bound methods of this context's own UDP
    interface are wrapped; other contexts in the process are unaffected."""
    interface = _udp_interface(ctx)
    send, received = interface.send, interface.datagram_msg_received
    recent_con: OrderedDict[tuple[Any, int], None] = OrderedDict()

    def counting_send(message: aiocoap.Message) -> None:
        send(message)
        counters.messages_sent += 1
        counters.bytes_sent += len(message.encode())
        if message.mtype == aiocoap.CON:
            key = (message.remote.sockaddr, message.mid)
            if key in recent_con:
                counters.retransmissions += 1
            else:
                recent_con[key] = None
                if len(recent_con) > 4096:
                    recent_con.popitem(last=False)

    def counting_received(data: bytes, ancdata: Any, flags: int, address: Any) -> None:
        counters.messages_received += 1
        counters.bytes_received += len(data)
        try:
            received(data, ancdata, flags, address)
        except UnicodeDecodeError:  # aiocoap 0.4.17's parser lets a non-UTF-8 string option escape: drop it
            log.debug("dropped a datagram from %s: string option is not UTF-8", address)

    interface.send = counting_send
    interface.datagram_msg_received = counting_received


def _tolerate_late_events(ctx: aiocoap.Context) -> None:
    """Survive a response or ICMP error for a request the caller gave up on.

    aiocoap 0.4.17 drops interest in a cancelled request only in a
    done-callback; a response or ICMP error handled before that callback runs
    hits the cancelled future, and the InvalidStateError escapes through the
    socket callback (which can close the context's socket).  The event has
    nobody to go to, so it is dropped here, on this context's message manager
    only."""
    manager = ctx.request_interfaces[0].token_interface
    dispatch_message, dispatch_error = manager.dispatch_message, manager.dispatch_error

    def tolerant_dispatch_message(message: aiocoap.Message) -> None:
        try:
            dispatch_message(message)
        except asyncio.InvalidStateError:
            log.debug("late response from %s for an abandoned request", message.remote)

    def tolerant_dispatch_error(exc: Exception, remote: Any) -> None:
        try:
            dispatch_error(exc, remote)
        except asyncio.InvalidStateError:
            log.debug("late error for an abandoned request to %s: %s", remote, exc)

    manager.dispatch_message = tolerant_dispatch_message
    manager.dispatch_error = tolerant_dispatch_error


class CoapServerTransport:
    """Serves a :class:`Service` over CoAP/UDP.

    The server's confirmable messages (Observe notifications) follow a
    retransmission profile too, with its own per-peer estimates."""

    def __init__(
        self,
        ctx: aiocoap.Context,
        endpoint: Endpoint,
        counters: TrafficCounters,
        retransmission: RetransmissionController,
    ) -> None:
        self._ctx = ctx
        self.endpoint = endpoint
        self.counters = counters
        self.retransmission = retransmission

    @classmethod
    async def start(
        cls, service: Service, endpoint: Endpoint, retransmission: TransmissionProfile | str = "adaptive"
    ) -> "CoapServerTransport":
        host = _resolve_host(endpoint.host)
        _check_port_free(host, endpoint.port)
        site = aiocoap.resource.Site()
        site.add_resource(
            [".well-known", "core"],
            aiocoap.resource.WKCResource(site.get_resources_as_linkheader, impl_info=None),
        )
        controller = RetransmissionController(retransmission)
        for info in service.resources():
            segments = [s for s in info.path.split("/") if s]
            site.add_resource(segments, _ServiceResource(service, info, controller))
        logger = logging.getLogger("coapkb.coap.server")
        if not any(isinstance(f, _RateLimitFilter) for f in logger.filters):
            logger.addFilter(_RateLimitFilter())
        try:
            ctx = await aiocoap.Context.create_server_context(
                site, bind=(host, endpoint.port), transports=["udp6"], loggername=logger.name
            )
        except OSError as exc:
            raise TransportError(f"cannot serve CoAP on {endpoint.hostport}: {exc.strerror or exc}") from None
        controller.install(ctx)
        _tolerate_late_events(ctx)
        port = _udp_interface(ctx)._local_port()
        counters = TrafficCounters()
        _count_traffic(ctx, counters)
        return cls(ctx, Endpoint("coap", endpoint.host, port), counters, controller)

    def describe(self) -> dict[str, Any]:
        return self.retransmission.as_dict()

    async def aclose(self) -> None:
        self.retransmission.uninstall(self._ctx)
        await self._ctx.shutdown()


# --------------------------------------------------------------------------- client

class CoapClientTransport:
    """Sends requests over CoAP/UDP.

    Confirmable retransmission follows a profile (``rfc7252``,
    ``lossy-fixed`` or ``adaptive``: a CoCoA-style RTO per peer), applied by
    a :class:`RetransmissionController` hooked into this context only."""

    def __init__(self, ctx: aiocoap.Context, retransmission: RetransmissionController) -> None:
        self._ctx = ctx
        self.retransmission = retransmission
        self.counters = TrafficCounters()
        _count_traffic(ctx, self.counters)

    @classmethod
    async def create(cls, retransmission: TransmissionProfile | str = "adaptive") -> "CoapClientTransport":
        """``retransmission``: a profile or its name (see :data:`coapkb.transport.coap.reliability.rto.PROFILES`)."""
        controller = RetransmissionController(retransmission)
        ctx = await aiocoap.Context.create_client_context(transports=["udp6"], loggername="coapkb.coap.client")
        controller.install(ctx)
        _tolerate_late_events(ctx)
        return cls(ctx, controller)

    def describe(self) -> dict[str, Any]:
        """Retransmission profile and per-peer estimates, for the agent's record."""
        return self.retransmission.as_dict()

    def _message(self, peer: Endpoint, request: Request, observe: bool = False) -> aiocoap.Message:
        msg = aiocoap.Message(
            code=_METHOD_CODES[request.method],
            uri=f"coap://{peer.hostport}{request.path}",
            payload=request.payload,
            transport_tuning=self.retransmission.tuning_for(peer),
        )
        query = [f"{k}={v}" for k, v in request.query.items()]
        if request.payload and request.method in (Method.FETCH, Method.POST):
            query.append(f"{BODY_HASH_PARAM}={body_hash(request.payload)}")
        msg.opt.uri_query = tuple(query)
        if request.content_format is not None:
            msg.opt.content_format = request.content_format
        if request.accept is not None:
            msg.opt.accept = request.accept
        if request.etags:
            msg.opt.etags = request.etags
        if observe:
            msg.opt.observe = 0
        return msg

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        pending = self._ctx.request(self._message(peer, request))
        try:
            async with asyncio.timeout(timeout):
                try:
                    return _response_from_message(await pending.response)
                except (aiocoap.error.ConRetransmitsExceeded, aiocoap.error.NetworkError) as exc:
                    raise PeerUnreachable(f"no answer from {peer}: {exc}") from None
                except aiocoap.error.Error as exc:
                    raise TransportError(f"request to {peer} failed: {exc}") from None
        except TimeoutError:
            raise PeerUnreachable(f"no answer from {peer} within {timeout:g}s") from None

    async def observe(self, peer: Endpoint, request: Request) -> AsyncIterator[Response]:
        pending = self._ctx.request(self._message(peer, request, observe=True))
        try:
            try:
                first = await pending.response
            except (aiocoap.error.ConRetransmitsExceeded, aiocoap.error.NetworkError) as exc:
                raise PeerUnreachable(f"no answer from {peer}: {exc}") from None
            yield _response_from_message(first)
            if pending.observation is None:
                return
            async for notification in pending.observation:
                yield _response_from_message(notification)
        finally:
            if pending.observation is not None and not pending.observation.cancelled:
                pending.observation.cancel()

    async def aclose(self) -> None:
        self.retransmission.uninstall(self._ctx)
        await self._ctx.shutdown()


def _response_from_message(msg: aiocoap.Message) -> Response:
    return Response(
        status=code_to_status(msg.code),
        payload=msg.payload,
        content_format=None if msg.opt.content_format is None else int(msg.opt.content_format),
        max_age=msg.opt.max_age,
        etag=msg.opt.etag,
    )

