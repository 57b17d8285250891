"""OSCORE (RFC 8613) keyed by EDHOC (RFC 9528) on coapkb's CoAP transport.

aiocoap 0.4.17 does OSCORE and both EDHOC roles; coapkb adds what a team
needs around them.  :class:`ClientSecurity` runs EDHOC once per peer on
first contact (concurrent first requests share the run), through the
client's reliability layer, with message_3 in its own exchange, and keeps
the OSCORE context; a peer that lost its context answers an unprotected
4.01 and the client keys again (:meth:`ClientSecurity.forget`).
:class:`ServerSecurity` wraps aiocoap's OSCORE site: one identity per robot,
a 4.01 also to a NON request in an unknown context, bounded and aging
EDHOC responder state with a rate on message_1, replays refused; it names
the member behind each request's context (:meth:`ServerSecurity.sender`)
and carries the team's rules (:mod:`.policy`), which the transport holds
every resource but ``/.well-known/core`` to.

docs/security.md ("How it works, and what aiocoap 0.4.17 needed")
specifies each of these and why; docs/aiocoap.md lists the aiocoap
internals touched here; docs/flood.md the bounds.
"""

from __future__ import annotations

import asyncio
import contextvars
import io
import logging
import math
import secrets
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import aiocoap
import aiocoap.error
import aiocoap.meta
import cbor2
import lakers
from aiocoap import edhoc as aiocoap_edhoc
from aiocoap import oscore
from aiocoap.credentials import CredentialsMap
from aiocoap.numbers.codes import POST
from aiocoap.numbers.types import NON
from aiocoap.oscore_sitewrapper import OscoreSiteWrapper
from aiocoap.transports.oscore import OSCOREAddress, TransportOSCORE

from ..cancelling import cancel_and_wait
from ..transport.base import Endpoint, RateLimitFilter, TransportError
from ..transport.coap.security import HandshakePost
from .errors import SecurityError
from .keys import CIPHER_SUITE, EDHOC_METHOD, TeamIdentity, TeamMember
from .policy import AccessPolicy, TeamRules

log = logging.getLogger(__name__)

EDHOC_PATH = (".well-known", "edhoc")
#: Prefix of the credentials-map labels of trusted peers; aiocoap reports
#: the label as the authenticated claim of a context.
_MEMBER_LABEL = ":member/"
_OWN_LABEL = ":own"
#: EDHOC sessions a robot's server keeps as responder.  A session is half
#: open from message_1 until a member's message_3 completes it: anyone on
#: the link can open one, so at most ``HALF_OPEN_MAX`` are kept (enough for a
#: central server's team of 99 keying at once: a central server for 60 robots
#: that kept 32 dropped members' sessions before their message_3), none for longer than
#: ``HALF_OPEN_S`` (a member's message_3 follows within a few round trips),
#: the oldest dropped first.  Complete sessions belong to members: one per
#: member is kept (a member that keys again replaces its older one), and
#: half-open ones only get the identifiers complete ones leave, so a flood of
#: message_1 never pushes a teammate's session out.
HALF_OPEN_MAX = 128
HALF_OPEN_S = 30.0
#: The connection identifiers (C_R, the OSCORE Recipient ID) a responder
#: gives its sessions: every one-byte identifier (RFC 9528 section 3.3.2),
#: those sent as a one-byte CBOR integer first, then those sent as a
#: one-byte byte string (one byte more in message_2 and message_3; the
#: OSCORE kid stays one byte).  aiocoap 0.4.17 offers only the 48 integers,
#: and its message_3 parser refuses 23 (``-24 <= c_r < 23``): a central
#: server with 60 robots ran out, and its EDHOC answered 5.00 "Too many
#: contexts" or met a message_3 whose session had been given away.
ONE_BYTE_IDENTIFIERS: tuple[bytes, ...] = tuple(
    bytes([b]) for b in sorted(range(256), key=lambda b: not (b < 0x17 or 0x20 <= b < 0x38)) if b != 0x17
)
#: Identifiers a responder has for complete sessions, less the one the
#: initiator chose.  When complete sessions alone would take them all, the
#: one used least recently goes (its member keys again on its next request).
RESPONDER_IDENTIFIERS = len(ONE_BYTE_IDENTIFIERS) - 1
#: message_1 a responder takes on per second, in bursts of up to
#: ``HALF_OPEN_MAX``.  Each costs it key generation and two ECDH operations
#: (about a millisecond): a stranger sending a thousand per second would
#: otherwise take a robot's whole CPU from the teammates it serves.  The
#: rest are answered 5.03 with Max-Age (RFC 7252 section 5.9.3.4) at the
#: cost of parsing them; a member's initiator waits that long and tries
#: again.  Members already keyed are not affected (docs/flood.md).
EDHOC_STARTS_PER_S = 20.0
#: How long a member's initiator waits at most when told to come back later.
EDHOC_RETRY_MAX_S = 5.0
EDHOC_BUSY_RETRIES = 6
#: Handshakes started again from message_1 when message_3 met no session
#: (or a broken one) at the responder; the request's own time bounds them too.
HANDSHAKE_RESTARTS = 3


class EdhocFailed(SecurityError, TransportError):
    """EDHOC with a peer failed: refused, not a teammate, or a bad message.
    A transport failure too, so callers fail over as for a dead peer."""

    def __init__(self, message: str, code: Any = None) -> None:
        super().__init__(message)
        #: The responder's error code, when it refused a message.
        self.code = code


class SessionGone(EdhocFailed):
    """The responder refused message_3: it no longer had the session."""


class MissingContext(SecurityError, aiocoap.error.Error):
    """A secured client found no OSCORE context for a request (a concurrent
    re-key dropped it): handled as a lost context."""


#: What a request over a context the peer no longer has ends in: an
#: unprotected error answer (4.01 here, 4.00 from other servers), or one that
#: does not decrypt.
CONTEXT_LOST = (oscore.NotAProtectedMessage, oscore.ProtectionInvalid, MissingContext)


def verify() -> None:
    """Check aiocoap's version and every internal name used here (the
    adapter keeps the list: :func:`~coapkb.transport.coap.aiocoap_adapter.verify_oscore`);
    raises :class:`~coapkb.transport.coap.aiocoap_adapter.UnsupportedAiocoapVersion`."""
    from ..transport.coap.aiocoap_adapter import verify_oscore

    verify_oscore()


def _edhoc_credentials(identity: TeamIdentity | None, peer: TeamMember | None) -> aiocoap_edhoc.EdhocCredentials:
    own: dict[str, Any] = {}
    if identity is not None:
        own = {
            "own_cred": identity.member.aiocoap_cred(),
            "own_cred_style": "by-key-id",
            # By value, never through a file name aiocoap would log on error.
            "private_key": {1: 2, -1: 1, -4: identity.private_d},
        }
    return aiocoap_edhoc.EdhocCredentials(
        suite=CIPHER_SUITE, method=EDHOC_METHOD, peer_cred=None if peer is None else peer.aiocoap_cred(),
        use_combined_edhoc=False, **own,
    )


@dataclass
class HandshakeStats:
    """One EDHOC run as the initiator saw it (CoAP payloads, both directions)."""

    peer: str
    round_trips: int = 0
    bytes_sent: int = 0
    bytes_received: int = 0
    seconds: float = 0.0


def _con_post(ctx: aiocoap.Context) -> HandshakePost:
    async def post(peer: Endpoint, payload: bytes) -> aiocoap.Message:
        request = aiocoap.Message(code=POST, uri=f"coap://{peer.hostport}/.well-known/edhoc", payload=payload)
        return await ctx.request(request).response

    return post


def _message_3_identifier(payload: bytes) -> bytes | None:
    """The C_R a message_3 request names (RFC 9528 appendix A.2: it comes
    first, a one-byte integer as its byte, else a byte string)."""
    try:
        c_r = cbor2.load(io.BytesIO(payload))  # the first item only
    except Exception:  # noqa: BLE001 - garbage names no session
        return None
    if isinstance(c_r, int) and not isinstance(c_r, bool):
        return cbor2.dumps(c_r)
    return c_r if isinstance(c_r, bytes) else None


def _encode_c_r(c_r: bytes) -> bytes:
    # RFC 9528 section 3.3.2: a one-byte identifier that is a CBOR integer
    # is sent as is; anything else as a CBOR byte string.
    if len(c_r) == 1 and (0 <= c_r[0] < 24 or 0x20 <= c_r[0] < 0x38):
        return c_r
    return cbor2.dumps(c_r)


class ClientSecurity:
    """A client's EDHOC-derived OSCORE contexts, one per peer, kept (the
    CoAP transport's :class:`~coapkb.transport.coap.security.CoapClientSecurity`)."""

    context_lost = CONTEXT_LOST

    def __init__(self, identity: TeamIdentity, expected: dict[str, str] | None = None) -> None:
        self.identity = identity
        #: Which member must answer at an endpoint (``host:port`` -> name),
        #: where known; other endpoints accept any member of the trust list.
        self.expected = dict(expected or {})
        self._runs: dict[str, asyncio.Task[Any]] = {}
        self.handshakes: list[HandshakeStats] = []
        #: Members authenticated at each endpoint.
        self.peers: dict[str, TeamMember] = {}

    @staticmethod
    def _key(peer: Endpoint) -> str:
        return f"coap://{peer.hostport}/*"

    def install(self, ctx: aiocoap.Context) -> None:
        install_oscore(ctx)

    async def ensure(self, ctx: aiocoap.Context, peer: Endpoint, post: HandshakePost | None = None) -> None:
        """An OSCORE context for ``peer`` in ``ctx``'s client credentials
        (EDHOC on first contact; callers racing here share one run).
        ``post(peer, payload)`` carries one EDHOC message and returns the
        answer (the client transport's, with its retries); default: one
        aiocoap CON request."""
        key = self._key(peer)
        if key in ctx.client_credentials:
            return
        run = self._runs.get(key)
        if run is None:
            run = asyncio.get_running_loop().create_task(
                self._establish(ctx, peer, post or _con_post(ctx)), name=f"edhoc {peer}"
            )
            self._runs[key] = run
            run.add_done_callback(self._run_done(key))
        # A caller's timeout must not cancel the run the others wait for.
        await asyncio.shield(run)

    def _run_done(self, key: str) -> Callable[[asyncio.Task[Any]], None]:
        def done(task: asyncio.Task[Any]) -> None:
            if self._runs.get(key) is task:
                del self._runs[key]
            # Its waiters may all have given up (their timeouts, a shutdown):
            # the outcome is theirs to see, not asyncio's to log.
            if not task.cancelled():
                task.exception()

        return done

    def context(self, ctx: aiocoap.Context, peer: Endpoint) -> Any:
        """The OSCORE context in use for ``peer`` (None before EDHOC)."""
        return ctx.client_credentials.get(self._key(peer))

    def forget(self, ctx: aiocoap.Context, peer: Endpoint, stale: Any = None) -> None:
        """Drop ``peer``'s context: the next request runs EDHOC again.  With
        ``stale``, only if that is still the one in use: of several requests
        that met the lost context at once, the first re-keys and the others
        use its new context instead of throwing it away again."""
        key = self._key(peer)
        if stale is None or ctx.client_credentials.get(key) is stale:
            ctx.client_credentials.pop(key, None)

    async def _establish(self, ctx: aiocoap.Context, peer: Endpoint, post: HandshakePost) -> None:
        """EDHOC with ``peer``; again from message_1 (up to
        :data:`HANDSHAKE_RESTARTS` times) if the responder no longer had the
        session when message_3 came, or could not complete it (4.00, 5.00: a
        central server keying with 99 robots at once, on a lossy link)."""
        for restart in range(HANDSHAKE_RESTARTS + 1):
            try:
                await self._handshake(ctx, peer, post)
                return
            except SessionGone as exc:
                if restart == HANDSHAKE_RESTARTS:
                    raise
                log.info("%s; keying with %s again", exc, peer)

    async def _handshake(self, ctx: aiocoap.Context, peer: Endpoint, post: HandshakePost) -> None:
        loop = asyncio.get_running_loop()
        started = loop.time()
        stats = HandshakeStats(str(peer))
        initiator = lakers.EdhocInitiator()
        c_i = bytes([secrets.randbelow(24)])
        message_1 = initiator.prepare_message_1(c_i)
        # CoAP transport of EDHOC (RFC 9528 appendix A.2): message_1 follows CBOR true.
        message_2 = await self._post(post, peer, cbor2.dumps(True) + message_1, stats)
        try:
            c_r, id_cred_r, ead_2 = initiator.parse_message_2(message_2)
        except Exception as exc:  # noqa: BLE001 - lakers raises plain exceptions for malformed messages
            raise EdhocFailed(f"EDHOC with {peer}: bad message_2 ({exc})") from None
        if any(item.is_critical() for item in ead_2):
            raise EdhocFailed(f"EDHOC with {peer}: critical EAD in message_2")
        member = self._responder(peer, id_cred_r)
        try:
            initiator.verify_message_2(self.identity.private_d, self.identity.member.ccs, member.ccs)
        except Exception:  # noqa: BLE001 - lakers raises plain exceptions
            raise EdhocFailed(f"EDHOC with {peer}: message_2 does not verify against {member.name}'s credential") from None
        context = _InitiatorContext(
            initiator, c_i, c_r, aiocoap_edhoc.OwnCredStyle.ByKeyId, logging.getLogger("coapkb.security.edhoc")
        )
        try:
            message_4 = await self._post(post, peer, _encode_c_r(c_r) + context.take_message_3(), stats)
        except EdhocFailed as exc:
            if exc.code in (aiocoap.BAD_REQUEST, aiocoap.INTERNAL_SERVER_ERROR):
                raise SessionGone(f"EDHOC with {peer}: message_3 refused ({exc.code}: the session is gone or "
                                  f"broken there)") from None
            raise
        try:
            context.complete_with_message_4(message_4)
        except Exception:  # noqa: BLE001 - lakers raises plain exceptions
            raise EdhocFailed(f"EDHOC with {peer}: bad message_4") from None
        stats.seconds = loop.time() - started
        self.handshakes.append(stats)
        self.peers[peer.hostport] = member
        ctx.client_credentials[self._key(peer)] = context
        log.debug("EDHOC with %s (%s) done in %.3f s", peer, member.name, stats.seconds)

    async def _post(self, post: HandshakePost, peer: Endpoint, payload: bytes, stats: HandshakeStats) -> bytes:
        for _ in range(EDHOC_BUSY_RETRIES):
            stats.round_trips += 1
            stats.bytes_sent += len(payload)
            try:
                response = await post(peer, payload)
            except (aiocoap.error.ConRetransmitsExceeded, aiocoap.error.NetworkError) as exc:
                raise TransportError(f"EDHOC with {peer}: no answer ({exc})") from None
            stats.bytes_received += len(response.payload)
            if response.code != aiocoap.SERVICE_UNAVAILABLE:
                break
            # The responder is taking on no more handshakes now: it says when to come back.
            await asyncio.sleep(min(float(response.opt.max_age or 1), EDHOC_RETRY_MAX_S))
        if not response.code.is_successful():
            detail = response.payload.decode("utf-8", "replace")[:80]
            raise EdhocFailed(f"EDHOC with {peer} refused: {response.code} {detail}".rstrip(), code=response.code)
        return bytes(response.payload)

    def _responder(self, peer: Endpoint, id_cred_r: bytes) -> TeamMember:
        """The trust list's member whose credential the responder named."""
        trust = self.identity.trust
        try:
            parsed = cbor2.loads(id_cred_r)
        except (ValueError, cbor2.CBORDecodeError):
            parsed = None
        member = None
        if isinstance(parsed, dict) and isinstance(parsed.get(4), bytes):
            member = trust.by_kid(parsed[4])
        elif isinstance(parsed, dict) and isinstance(parsed.get(14), dict):
            member = trust.by_ccs(cbor2.dumps(parsed[14], canonical=True))
        if member is None:
            raise EdhocFailed(f"EDHOC with {peer}: it presented a credential not in the team's trust list")
        want = self.expected.get(peer.hostport)
        if want is not None and member.name != want:
            raise EdhocFailed(f"EDHOC with {peer}: expected {want}, but {member.name} answered")
        return member


@dataclass
class _WireRequests:
    """The wire (outer) requests one OSCORE request made, and whether its
    requester has lost interest."""

    made: list[Any] = field(default_factory=list)
    ended: bool = False

    def end(self) -> None:
        self.ended = True
        for wire in self.made:
            _end_wire_request(wire)


def _end_wire_request(wire: Any) -> None:
    if wire.request_observes:
        _cancel_observation(wire)
    elif not wire.response.done():
        # Frees the token; the OSCORE task waiting on it ends (_OSCORETransport._request).
        wire.response.cancel()


def _cancel_observation(wire: Any) -> None:
    observation = getattr(wire, "observation", None)
    if observation is not None and not observation.cancelled:
        observation.cancel()


_CURRENT: contextvars.ContextVar[_WireRequests | None] = contextvars.ContextVar("coapkb_oscore_wire", default=None)


class _WireRecorder:
    """The context, as aiocoap's OSCORE transport sees its wire: notes each
    wire request of the OSCORE request being processed."""

    def __init__(self, ctx: aiocoap.Context) -> None:
        self._ctx = ctx

    def __getattr__(self, name: str) -> Any:
        return getattr(self._ctx, name)

    def request(self, message: aiocoap.Message, *args: Any, **kwargs: Any) -> Any:
        if message.opt.observe is not None:
            # A registration without aiocoap's block-wise wrapper (a
            # notification fits one datagram): cancelling that wrapper's
            # observation before the first answer failed with
            # TypeError('invalid exception object') and left the token
            # registered, so the peer's notifications were acknowledged for ever.
            kwargs["handle_blockwise"] = False
        wire = self._ctx.request(message, *args, **kwargs)
        # Registrations get their observation cancelled; plain requests their
        # response (cancelling a plain request's observation made aiocoap
        # fail its response with TypeError('invalid exception object')).
        wire.request_observes = message.opt.observe is not None
        current = _CURRENT.get()
        if current is not None:
            current.made.append(wire)
            if current.ended:  # abandoned before it was even sent
                _end_wire_request(wire)
        return wire


class _OSCORETransport(TransportOSCORE):
    """aiocoap 0.4.17's OSCORE request interface, with an abandoned Observe
    registration ended on the wire too.  aiocoap cannot cancel one ("no way
    yet to cancel observations"): the peer kept notifying, and this client
    kept acknowledging, every registration the robust layer had given up
    (a lost answer, a hedge copy); at 20 % loss a robot sent six times the
    notifications.  Cancelled, the next notification is answered with a
    Reset and the peer forgets the observation (RFC 7641 section 3.6)."""

    def __init__(self, ctx: aiocoap.Context) -> None:
        super().__init__(ctx, _WireRecorder(ctx))

    async def fill_or_recognize_remote(self, message: aiocoap.Message) -> bool:
        """Claim every request but EDHOC's own: a secured client never sends
        one unprotected.  (Between the client's check for a context and
        this, a concurrent re-key may have dropped it; the request then
        fails here, as after a lost context, and is tried again.)"""
        if await super().fill_or_recognize_remote(message):
            return True
        if message.opt.uri_path == EDHOC_PATH or message.opt.oscore is not None:
            return False  # EDHOC, or a protected (outer) message on its way to the wire
        raise MissingContext(f"no OSCORE context for {message.get_request_uri()}")

    def request(self, request: Any) -> None:
        """aiocoap's own, with a done-callback that also takes cancellation:
        Ctrl-C cancels every task, these among them, and aiocoap's (which
        handles only ``Exception``) logged each as a traceback."""
        tracked = _WireRequests()
        token = _CURRENT.set(tracked)
        try:  # the task starts in a copy of this context: it sees ``tracked``
            task = self.loop.create_task(self._request(request), name=f"OSCORE request {request!r}")
        finally:
            _CURRENT.reset(token)
        self._tasks.add(task)
        task.add_done_callback(lambda done: self._request_done(done, request, tracked))
        request.on_interest_end(tracked.end)

    async def shutdown(self) -> None:
        """End the requests still running.  aiocoap leaves them to the
        transports below, which end the wire requests but not an
        observation's loop reading one: it stayed pending, and was reported
        when collected ("Task was destroyed but it is pending") once a
        process had run a second team."""
        await cancel_and_wait(self._tasks)
        await super().shutdown()

    def _request_done(self, task: asyncio.Task[None], request: Any, tracked: _WireRequests) -> None:
        self._tasks.discard(task)
        if task.cancelled():
            if tracked.ended:
                # Its wire request was ended because the requester gave up (a
                # NON try the robust layer abandoned): nobody waits for an outcome.
                return
            error: BaseException = aiocoap.error.LibraryShutdown()  # the loop is ending
        elif (raised := task.exception()) is not None:
            error = raised
        else:
            return
        if request._event_callbacks is not False:  # still open: aiocoap logs an error added after its end
            request.add_exception(error)


def install_oscore(ctx: aiocoap.Context) -> None:
    """Put the OSCORE request interface first in ``ctx`` (so it claims every
    request it holds a context for before plain UDP does)."""
    verify()
    ctx.request_interfaces.insert(0, _OSCORETransport(ctx))


class _InitiatorContext(aiocoap_edhoc.EdhocInitiatorContext):
    """aiocoap's initiator context, with message_3 sent by coapkb in its own
    exchange (never piggybacked on a request)."""

    def take_message_3(self) -> bytes:
        message_3 = self.message_3_to_include()
        if message_3 is None:
            raise SecurityError("EDHOC message_3 already sent")
        return bytes(message_3)

    @property
    def authenticated_claims(self) -> list[str]:
        return []


def _context_not_found(pipe: Any) -> None:
    """Answer, unprotected, that the request's OSCORE context is not here (4.01)."""
    pipe.add_response(aiocoap.Message(code=aiocoap.UNAUTHORIZED, max_age=0, payload=b"Security context not found"),
                      is_last=True)


class _AnsweredPipe:
    """A request's pipe that notes whether anything answered it."""

    def __init__(self, pipe: Any) -> None:
        self._pipe = pipe
        self.answered = False

    def add_response(self, response: aiocoap.Message, is_last: bool = False) -> None:
        self.answered = True
        self._pipe.add_response(response, is_last=is_last)

    def add_exception(self, exception: BaseException) -> None:
        self.answered = True
        self._pipe.add_exception(exception)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._pipe, name)


class _TeamSiteWrapper(OscoreSiteWrapper):
    def __init__(self, inner_site: Any, credentials: CredentialsMap, *,
                 responder_identifiers: int = RESPONDER_IDENTIFIERS) -> None:
        super().__init__(inner_site, credentials)
        #: The complete responder sessions kept at most (see ``RESPONDER_IDENTIFIERS``).
        self.responder_identifiers = responder_identifiers
        self.log = logging.getLogger("coapkb.security.server")
        # aiocoap logs a stranger's undecryptable message or stray EDHOC
        # message as an error, once per datagram.
        RateLimitFilter.install(self.log, peer_errors=True)
        #: When each responder session (by its label in the credentials) was
        #: opened, and when its member last sent a request through it.
        self._opened: dict[str, float] = {}
        self._used: dict[int, float] = {}  # id() of the session -> time
        #: Tokens for message_1 (``EDHOC_STARTS_PER_S``), and when they were counted.
        self._start_tokens = float(HALF_OPEN_MAX)
        self._tokens_at = 0.0
        #: message_1 answered 5.03 for want of a token, and taken on.
        self.refused_starts = 0
        self.taken_starts = 0
        #: Identifiers of sessions dropped lately -> when (:meth:`_free_identifier`).
        self._resting: dict[bytes, float] = {}

    def _get_edhoc_identity(self, origin: str) -> aiocoap_edhoc.EdhocCredentials | None:
        # One identity per robot, whatever host name the client asked for.
        own = self.server_credentials.get(_OWN_LABEL)
        return own if isinstance(own, aiocoap_edhoc.EdhocCredentials) else None

    async def render_to_pipe(self, pipe: Any) -> None:
        request = pipe.request
        if request.opt.uri_path == EDHOC_PATH and request.payload[:1] == cbor2.dumps(True):
            now = asyncio.get_running_loop().time()
            wait = self._take_start_token(now)
            if wait:
                self.refused_starts += 1
                pipe.add_response(aiocoap.Message(code=aiocoap.SERVICE_UNAVAILABLE, max_age=wait), is_last=True)
                return
            self.taken_starts += 1
            self._prune(now)
            before = set(self.server_credentials)
            await super().render_to_pipe(pipe)
            for label in set(self.server_credentials) - before:
                self._opened[label] = now
            return
        elif request.opt.oscore is not None:
            try:
                context = self.server_credentials.find_oscore(oscore.verify_start(request))
            except KeyError:
                if request.mtype == NON:  # (aiocoap answers a CON itself)
                    _context_not_found(pipe)
                    return
            except oscore.NotAProtectedMessage:
                pass
            else:
                self._used[id(context)] = asyncio.get_running_loop().time()
                # aiocoap 0.4.17's EDHOC contexts lack the attribute its replay
                # check reads (a replay became a 5.00 and a traceback).  Their
                # replay window starts empty and valid (a fresh key), so there
                # is nothing to recover with Echo (RFC 8613 appendix B.1.2).
                if not hasattr(context, "echo_recovery"):
                    context.echo_recovery = None
                if request.mtype == NON:
                    # aiocoap drops a NON request its context cannot decrypt
                    # without a word.  That happens when a session was dropped
                    # and its identifier given to another member's: the first
                    # member must hear that its context is gone, or it never
                    # keys again (RFC 8613 section 8.2 lets a server answer).
                    watched = _AnsweredPipe(pipe)
                    await super().render_to_pipe(watched)
                    if not watched.answered:
                        _context_not_found(pipe)
                    return
        await super().render_to_pipe(pipe)

    def _process_edhoc_msg12(self, pipe: Any) -> None:
        """EDHOC message_1 as responder, with a connection identifier from
        :data:`ONE_BYTE_IDENTIFIERS` (see there); the session is kept as
        aiocoap keeps its own, and its message_3 goes through aiocoap."""
        own = self._get_edhoc_identity("")
        if own is None:
            raise aiocoap.error.NotFound("no EDHOC identity here")
        responder = lakers.EdhocResponder(r=own.own_key.d, cred_r=cbor2.dumps(own.own_cred[14], canonical=True))
        try:
            c_i, ead_1 = responder.process_message_1(pipe.request.payload[1:])
        except Exception:  # noqa: BLE001 - lakers raises plain exceptions for malformed messages
            raise aiocoap.error.BadRequest("malformed EDHOC message_1") from None
        if any(item.is_critical() for item in ead_1):
            raise aiocoap.error.BadRequest("critical EAD in message_1")
        used = self.server_credentials.find_all_used_contextless_oscore_kid() | {bytes(c_i)}
        c_r = self._free_identifier(used, asyncio.get_running_loop().time())
        if c_r is None:  # _prune leaves one free; only a race gets here
            raise aiocoap.error.ServiceUnavailable("no free connection identifier")
        message_2 = responder.prepare_message_2(own.own_cred_style.as_lakers(), c_r, None)
        session = aiocoap_edhoc.EdhocResponderContext(responder, bytes(c_i), c_r, self.server_credentials, self.log)
        self.server_credentials[":" + secrets.token_hex(16)] = session
        pipe.add_response(aiocoap.Message(code=aiocoap.CHANGED, payload=bytes(message_2)), is_last=True)

    def _process_edhoc_msg34(self, pipe: Any) -> None:
        """EDHOC message_3 through aiocoap; one that does not complete its
        session (lakers: a MAC that does not verify, a session in another
        state) ends that session and is answered 4.00, not 5.00 with a
        traceback: the initiator starts over from message_1."""
        try:
            super()._process_edhoc_msg34(pipe)
        except (ValueError, RuntimeError) as exc:  # lakers raises these for a message_3 that does not fit
            c_r = _message_3_identifier(pipe.request.payload)
            for label, entry in list(self.server_credentials.items()):
                if (isinstance(entry, aiocoap_edhoc.EdhocResponderContext) and entry._incomplete
                        and bytes(entry.recipient_id) == c_r):
                    self._release(label, asyncio.get_running_loop().time())
            raise aiocoap.error.BadRequest(f"message_3 does not complete its session ({exc})") from None

    def _take_start_token(self, now: float) -> int:
        """0 if a message_1 may be taken on now, else the seconds to wait (at least 1)."""
        self._start_tokens = min(float(HALF_OPEN_MAX),
                                 self._start_tokens + (now - self._tokens_at) * EDHOC_STARTS_PER_S)
        self._tokens_at = now
        if self._start_tokens >= 1.0:
            self._start_tokens -= 1.0
            return 0
        return max(1, math.ceil((1.0 - self._start_tokens) / EDHOC_STARTS_PER_S))

    def sweep(self, now: float) -> None:
        """Forget the half-open sessions older than ``HALF_OPEN_S``."""
        for label, entry in list(self.server_credentials.items()):
            if (isinstance(entry, aiocoap_edhoc.EdhocResponderContext) and entry._incomplete
                    and now - self._opened.get(label, now) >= HALF_OPEN_S):
                self._release(label, now)

    def _prune(self, now: float) -> None:
        """Make room for one more half-open session: complete sessions first
        (see ``HALF_OPEN_MAX`` and ``RESPONDER_IDENTIFIERS``)."""
        self.sweep(now)  # the half-open sessions past their age first
        half_open: list[str] = []
        newest: dict[tuple[str, ...], str] = {}  # member's claims -> its latest complete session
        drop: list[str] = []
        for label, entry in self.server_credentials.items():  # oldest first
            if not isinstance(entry, aiocoap_edhoc.EdhocResponderContext):
                continue
            if entry._incomplete:
                half_open.append(label)
                continue
            member = tuple(entry.authenticated_claims)
            if member in newest:
                drop.append(newest[member])
            newest[member] = label
        complete = list(newest.values())
        # The new session needs one identifier; complete sessions keep theirs
        # unless they alone leave none (more members than identifiers).
        kept = self.responder_identifiers
        if len(complete) >= kept:
            complete.sort(key=lambda label: self._used.get(id(self.server_credentials[label]), 0.0))
            drop += complete[: len(complete) - kept + 1]
            complete = complete[len(complete) - kept + 1:]
        room = min(HALF_OPEN_MAX, kept - len(complete)) - 1
        drop += half_open[: max(0, len(half_open) - room)]
        for label in drop:
            self._release(label, now)

    def _release(self, label: str, now: float) -> None:
        """Forget a responder session; its identifier rests (see :meth:`_free_identifier`)."""
        entry = self.server_credentials.pop(label)
        self._opened.pop(label, None)
        self._used.pop(id(entry), None)
        self._resting[bytes(entry.recipient_id)] = now

    def _free_identifier(self, used: set[bytes], now: float) -> bytes | None:
        """The first identifier of :data:`ONE_BYTE_IDENTIFIERS` no session
        uses and none gave up within ``HALF_OPEN_S``: a message_3 still on
        its way for a session that was dropped then finds no session, instead
        of another member's half-open one (which it would break); the
        longest resting one when every free one rests."""
        for gone, since in list(self._resting.items()):
            if now - since >= HALF_OPEN_S:
                del self._resting[gone]
        free = [c for c in ONE_BYTE_IDENTIFIERS if c not in used]
        fresh = [c for c in free if c not in self._resting]
        if fresh:
            return fresh[0]
        return min(free, key=lambda c: self._resting[c], default=None)


@dataclass
class ServerSecurity:
    """A robot's server side: its EDHOC identity, the trust list, the policy
    (the CoAP transport's :class:`~coapkb.transport.coap.security.CoapServerSecurity`)."""

    identity: TeamIdentity
    policy: AccessPolicy = field(default_factory=AccessPolicy)
    #: The complete EDHOC sessions held as responder at most, one per
    #: connection identifier (``RESPONDER_IDENTIFIERS``).
    responder_identifiers: int = RESPONDER_IDENTIFIERS
    #: The site wrapper of the server this security serves (set by :meth:`wrap`).
    _site: Any = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        verify()
        self.rules = TeamRules(self.identity.trust, self.policy)
        self.credentials = CredentialsMap()
        self.credentials[_OWN_LABEL] = _edhoc_credentials(self.identity, None)
        for member in self.identity.trust.members:
            self.credentials[_MEMBER_LABEL + member.name] = _edhoc_credentials(None, member)

    def wrap(self, site: Any) -> Any:
        self._site = _TeamSiteWrapper(site, self.credentials, responder_identifiers=self.responder_identifiers)
        return self._site

    def sweep(self, now: float | None = None) -> None:
        """Forget the responder state that has aged out by ``now`` (the
        loop's time by default): half-open EDHOC sessions."""
        if self._site is not None:
            self._site.sweep(asyncio.get_running_loop().time() if now is None else now)

    @property
    def refused_starts(self) -> int:
        """message_1 answered 5.03 because the responder took on its rate of them."""
        return 0 if self._site is None else self._site.refused_starts

    @property
    def taken_starts(self) -> int:
        """message_1 taken on (within the responder's rate)."""
        return 0 if self._site is None else self._site.taken_starts

    def responder_sessions(self) -> tuple[int, int]:
        """(half open, complete) EDHOC sessions this server holds as responder."""
        entries = [e for e in self.credentials.values() if isinstance(e, aiocoap_edhoc.EdhocResponderContext)]
        half_open = sum(1 for e in entries if e._incomplete)
        return half_open, len(entries) - half_open

    def sender(self, request: aiocoap.Message) -> str | None:
        """The team member a request came from, or None if it was not protected."""
        remote = request.remote
        if not isinstance(remote, OSCOREAddress):
            return None
        for claim in getattr(remote.security_context, "authenticated_claims", ()):
            if isinstance(claim, str) and claim.startswith(_MEMBER_LABEL):
                member = self.identity.trust.by_name(claim[len(_MEMBER_LABEL):])
                return None if member is None else member.name
        return None
