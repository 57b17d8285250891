"""The CoAP client of a robot (and of ``coapkb query``).

Every request goes through the :class:`~.reliability.ReliabilityLayer`:
each try a NON request with a fresh token, Block2 answers fetched block by
block, each block its own exchange (a lost block costs one retry of that
block, not a restart).  Requests whose body needs Block1 (over 1024 bytes:
long SPARQL text) use aiocoap's confirmable exchanges, with its timers.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from typing import Any

import aiocoap
import aiocoap.error
from aiocoap.numbers.codes import POST
from aiocoap.numbers.constants import Unreliable
from aiocoap.numbers.types import NON
from aiocoap.optiontypes import BlockOption

from ..base import Endpoint, PeerGone, PeerTimeout, PeerUnreachable, TrafficCounters, TransportError
from ..messages import Request, Response
from .aiocoap_adapter import ContextHooks
from .mapping import message_from_request, response_from_message
from .reliability import ReliabilityLayer, make_reliability
from .reliability.layer import Attempt, ExchangeTimeout
from .reliability.notifications import NotificationPolicy, NotificationTuning
from .security import CoapClientSecurity

#: Largest body sent in one datagram (aiocoap's default block size).
MAX_SINGLE_BODY = 1024
#: Block-wise transfers started over before giving up on an answer that keeps changing.
MAX_TRANSFER_RESTARTS = 4
#: Unanswered requests in a row to a peer after which its OSCORE context is
#: dropped and the next request runs EDHOC again (see ``_secured``).
REKEY_AFTER_UNANSWERED = 2
#: Longest one EDHOC message may take with its retries (the request's own timeout usually ends it first).
EDHOC_TIMEOUT_S = 60.0
#: How long an Observe registration may take, retransmissions included, seconds.
REGISTRATION_TIMEOUT_S = 60.0
#: aiocoap's ways of saying that the peer did not answer.
_NO_ANSWER = (aiocoap.error.ConRetransmitsExceeded, aiocoap.error.NetworkError)



def _refused(exc: aiocoap.error.NetworkError) -> str:
    """What an ICMP error means for the user: usually that nothing serves there."""
    text = str(exc.args[0]) if exc.args else ""
    if "ECONNREFUSED" in text or "Connection refused" in text:
        return "nothing listens on that port (is the robot or server running there?)"
    if "EHOSTUNREACH" in text or "ENETUNREACH" in text:
        return "the host cannot be reached (is the address right?)"
    return text or "the network refused the request"

class _AbandonedTryFilter(logging.Filter):
    """aiocoap warns when a request is cancelled before its token was even
    registered; the layer abandons hedge copies and retries that way as a
    matter of course.  Under OSCORE aiocoap's protecting task outlives an
    abandoned try: its late answer (a warning), or its end at shutdown or
    when an abandoned observation is cancelled (an error naming
    LibraryShutdown or ObservationCancelled) is no news either."""

    def filter(self, record: logging.LogRecord) -> bool:
        msg = str(record.msg)
        if msg.startswith(("on_interest_end callback", "Response %r added after")):
            return False
        if msg.startswith("Discarded exception in") and record.args:
            event = record.args[0] if isinstance(record.args, tuple) else None
            exc = getattr(event, "exception", None)
            # aiocoap 0.4.17 fails a request abandoned before its first
            # answer with TypeError('invalid exception object') (it sets the
            # end-of-pipe marker, None, as the response's exception).
            abandoned = isinstance(exc, TypeError) and str(exc) == "invalid exception object"
            # A network error (ICMP port unreachable) for a try already given
            # up: the layer's own try, or the team stopping, says what matters.
            return not (abandoned or isinstance(exc, (aiocoap.error.LibraryShutdown, aiocoap.error.ObservationCancelled,
                                                      aiocoap.error.NetworkError)))
        return True


def _reply_bytes(message: aiocoap.Message) -> int:
    return len(message.payload) + 16  # header, token and the usual options


class CoapClientTransport:
    """Sends requests over CoAP/UDP, retried by a :class:`ReliabilityLayer`."""

    def __init__(self, ctx: aiocoap.Context, hooks: ContextHooks, reliability: ReliabilityLayer,
                 security: CoapClientSecurity | None = None) -> None:
        self._ctx = ctx
        #: Protects every request (OSCORE by EDHOC to every peer), or None.
        self.security = security
        #: Peer (host:port) -> its requests unanswered in a row under its current context.
        self._unanswered: dict[str, int] = {}
        self._hooks = hooks
        self.reliability = reliability
        self.counters: TrafficCounters = hooks.counters
        self._closed = False

    @classmethod
    async def create(
        cls, reliability: ReliabilityLayer | None = None, security: CoapClientSecurity | None = None,
    ) -> CoapClientTransport:
        """``reliability``: a layer (shared with the robot's server), or None for one of its own.
        ``security``: OSCORE keyed by EDHOC, or None (unprotected)."""
        logger = logging.getLogger("coapkb.coap.client")
        if not any(isinstance(f, _AbandonedTryFilter) for f in logger.filters):
            logger.addFilter(_AbandonedTryFilter())
        ctx = await aiocoap.Context.create_client_context(transports=["udp6"], loggername=logger.name)
        if security is not None:
            security.install(ctx)
        hooks = ContextHooks.of(ctx)
        if reliability is None:
            reliability = make_reliability()
        hooks.on_datagram = reliability.on_datagram
        hooks.set_con_policy(NotificationPolicy(reliability))  # Observe registrations (_register)
        return cls(ctx, hooks, reliability, security)

    def describe(self) -> dict[str, Any]:
        """The layer's settings and per-peer estimates, for the agent's record."""
        return self.reliability.as_dict()

    # ------------------------------------------------------------ requests

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        if self._closed:
            raise TransportError("the coap client transport is closed")
        try:
            message = await self._secured(peer, lambda: self._request_any(peer, request, timeout), timeout)
        except aiocoap.error.LibraryShutdown:
            raise TransportError("the coap client transport was closed") from None
        except (TimeoutError, ExchangeTimeout):
            raise PeerTimeout(f"no answer from {peer} within {timeout:g}s") from None
        except aiocoap.error.NetworkError as exc:  # ICMP: nobody listens there
            raise PeerGone(f"no answer from {peer}: {_refused(exc)}") from None
        except _NO_ANSWER as exc:
            raise PeerUnreachable(f"no answer from {peer}: {exc}") from None
        except aiocoap.error.Error as exc:
            raise TransportError(f"request to {peer} failed: {str(exc) or type(exc).__name__}") from None
        return response_from_message(message)

    async def _request_any(self, peer: Endpoint, request: Request, timeout: float) -> aiocoap.Message:
        if len(request.payload) <= MAX_SINGLE_BODY:
            return await self._request_blockwise(peer, request, timeout)
        return await self._request_con(peer, request)

    async def _secured(self, peer: Endpoint, exchange: Any, timeout: float | None = None) -> Any:
        """``exchange()`` under OSCORE when security is on, all within
        ``timeout``: EDHOC on first contact; a context the peer lost (it
        restarted) is re-keyed once, at once when the peer says so, after
        :data:`REKEY_AFTER_UNANSWERED` unanswered requests in a row when it
        was silent."""
        if self.security is None:
            async with asyncio.timeout(timeout):
                return await exchange()
        used = None
        try:
            async with asyncio.timeout(timeout):
                rekeyed = False
                while True:
                    await self.security.ensure(self._ctx, peer, post=self._edhoc_post)
                    used = self.security.context(self._ctx, peer)
                    try:
                        answer = await exchange()
                    except self.security.context_lost as exc:
                        if self.security.context(self._ctx, peer) is not used:
                            # Dropped here meanwhile (a concurrent request
                            # re-keyed): nothing is known of the peer; use
                            # the context that replaced it.
                            continue
                        if rekeyed:
                            raise
                        logging.getLogger("coapkb.security").warning(
                            "%s: our OSCORE context is gone there (%s); running EDHOC again", peer, type(exc).__name__)
                        self.security.forget(self._ctx, peer, stale=used)
                        rekeyed = True
                        continue
                    self._unanswered.pop(peer.hostport, None)
                    return answer
        except (TimeoutError, ExchangeTimeout, *_NO_ANSWER):
            # A peer that restarted may have handed our old key id to another
            # client; our requests then fail to decrypt there and a NON one
            # goes unanswered (RFC 8613 lets the server stay silent).  So
            # after unanswered requests in a row the next one re-keys instead
            # of repeating the silence until the peer is declared down.  Not
            # after one: a peer only slow (a loaded central server) would be
            # re-keyed over and over, and every request in flight on the old
            # context would fail with it.
            if used is not None:
                unanswered = self._unanswered[peer.hostport] = self._unanswered.get(peer.hostport, 0) + 1
                if unanswered >= REKEY_AFTER_UNANSWERED:
                    self._unanswered.pop(peer.hostport, None)
                    self.security.forget(self._ctx, peer, stale=used)
            raise

    async def _edhoc_post(self, peer: Endpoint, payload: bytes) -> aiocoap.Message:
        """One EDHOC message (POST /.well-known/edhoc, RFC 9528 appendix A.2),
        retried like any request: NON tries timed by the layer (aiocoap's
        CON would wait 2-3 s for each lost one on a slow link).  A repeated message_1
        gets a fresh message_2 (either one completes the run); a repeated
        message_3 the same message_4."""
        uri = f"coap://{peer.hostport}/.well-known/edhoc"

        def send(try_number: int) -> Attempt[aiocoap.Message]:
            if try_number:
                self.counters.retransmissions += 1
            msg = aiocoap.Message(code=POST, uri=uri, payload=payload, transport_tuning=Unreliable)
            msg.mtype = NON
            pending = self._ctx.request(msg, handle_blockwise=False)
            return Attempt(pending.response, cancel=lambda: _abandon(pending), handle=pending)

        answer, _ = await self.reliability.exchange(
            peer, send, timeout=EDHOC_TIMEOUT_S, request_bytes=len(payload) + 24,
            reply_key=("/.well-known/edhoc", None, False), reply_size=_reply_bytes,
        )
        return answer

    async def _request_con(self, peer: Endpoint, request: Request) -> aiocoap.Message:
        """An aiocoap confirmable request (block-wise for a large body)."""
        return await self._ctx.request(message_from_request(peer, request)).response

    async def _exchange(self, peer: Endpoint, request: Request, timeout: float, *,
                        block2: tuple[int, int] | None = None) -> tuple[aiocoap.Message, Attempt[aiocoap.Message]]:
        sent = 0

        def send(try_number: int) -> Attempt[aiocoap.Message]:
            nonlocal sent
            if sent:  # a retry or a hedge copy: the same request again, as a new exchange
                self.counters.retransmissions += 1
            sent += 1
            msg = message_from_request(peer, request)
            msg.mtype = NON
            if self.security is not None:
                # OSCORE builds the outer message afresh, keeping only the
                # tuning: without this it went CON, and aiocoap's NSTART=1
                # held every later try behind a lost one for 2-3 s.
                msg.transport_tuning = Unreliable
            if block2 is not None:
                msg.opt.block2 = BlockOption.BlockwiseTuple(block2[0], False, block2[1])
            pending = self._ctx.request(msg, handle_blockwise=False)
            return Attempt(pending.response, cancel=lambda: _abandon(pending), handle=pending)

        return await self.reliability.exchange(
            peer, send, timeout=timeout, request_bytes=len(request.payload) + 32,
            reply_key=(request.path, request.accept, block2 is not None), reply_size=_reply_bytes,
        )

    async def _request_blockwise(self, peer: Endpoint, request: Request, timeout: float) -> aiocoap.Message:
        """Block 0, then the rest block by block.  An answer whose ETag changes
        midway (a live resource, a retried block 0 that made the server start
        afresh) is fetched again from block 0 (RFC 7959 section 2.4)."""
        for _ in range(MAX_TRANSFER_RESTARTS):
            first, _ = await self._exchange(peer, request, timeout)
            block = first.opt.block2
            if block is None or not block.more:
                return first
            payload = bytearray(first.payload)
            number, szx = block.block_number, block.size_exponent
            while True:
                number += 1
                part, _ = await self._exchange(peer, request, timeout, block2=(number, szx))
                if part.code != first.code or part.opt.etag != first.opt.etag:
                    break  # another answer: start over
                if part.opt.block2 is None or part.opt.block2.block_number != number:
                    raise TransportError(f"{peer} answered block {number} out of order")
                payload += part.payload
                if not part.opt.block2.more:
                    whole = first.copy(payload=bytes(payload))
                    whole.opt.block2 = None
                    return whole
        raise TransportError(f"the answer from {peer} kept changing during its block-wise transfer")

    async def observe(self, peer: Endpoint, request: Request) -> AsyncIterator[Response]:
        if self._closed:
            raise TransportError("the coap client transport is closed")
        try:
            first, pending = await self._secured(peer, lambda: self._register(peer, request), REGISTRATION_TIMEOUT_S)
        except aiocoap.error.LibraryShutdown:
            raise TransportError("the coap client transport was closed") from None
        except (TimeoutError, ExchangeTimeout):
            raise PeerTimeout(f"no answer from {peer} to the observation") from None
        except aiocoap.error.NetworkError as exc:  # ICMP: nobody listens there
            raise PeerGone(f"no answer from {peer}: {_refused(exc)}") from None
        except _NO_ANSWER as exc:
            raise PeerUnreachable(f"no answer from {peer}: {exc}") from None
        try:
            yield response_from_message(first)
            if pending.observation is None:
                return
            try:
                async for notification in pending.observation:
                    yield response_from_message(notification)
            except aiocoap.error.LibraryShutdown:
                raise TransportError("the coap client transport was closed") from None
        finally:
            _abandon(pending)

    async def _register(self, peer: Endpoint, request: Request) -> tuple[aiocoap.Message, Any]:
        """An Observe registration, as one confirmable request.

        Not the layer's fresh exchange per try: every try that reached the
        server would be an observation of its own there (RFC 7641 keys one by
        endpoint and token), each sending the whole state at the next change
        until this client reset it -- on a lossy link a dozen per run, each
        holding the real notification behind it.  A CON's retransmissions
        keep its Message ID, so the server registers it once; their timers
        follow the layer's path estimates (the context's CON policy)."""
        msg = message_from_request(peer, request, observe=True)
        msg.transport_tuning = NotificationTuning  # CON, under OSCORE too
        pending = self._ctx.request(msg, handle_blockwise=False)
        try:
            return await pending.response, pending
        except BaseException:
            _abandon(pending)
            raise

    async def aclose(self) -> None:
        self._closed = True
        try:
            await self._ctx.shutdown()
        except (RuntimeError, asyncio.InvalidStateError) as exc:
            # aiocoap 0.4.17 (through OSCORE) errors an observation it has
            # already cancelled while shutting down, or a request whose caller
            # gave up on it (seen closing a feeder of 99 robots); the context is
            # closed anyway, and the error must not hide why the caller closed it.
            logging.getLogger("coapkb.coap.client").debug("closing the CoAP client: %s", exc)
            await self._hooks.close_socket()  # aiocoap's shutdown stopped before it
        self._hooks.remove()


def _abandon(pending: Any) -> None:
    """Stop waiting for a request's answer and end its observation, if any."""
    if not pending.response.done():
        pending.response.cancel()
    observation = getattr(pending, "observation", None)
    if observation is not None and not observation.cancelled:
        observation.cancel()
