"""The one place where coapkb touches aiocoap's private surface.

aiocoap is kept for messages, resources, Observe, block-wise transfer and
interop; everything else coapkb needs from it (per-context traffic counters,
per-peer retransmission timers through a :class:`ConPolicy`, tolerance of
late events and of a pending ICMP error met by another peer's send, the
block-wise cache's key and block extraction) reaches into names aiocoap
does not promise to keep.  They are all here, behind one version pin, and
:func:`verify` checks every one of them, so an upgrade fails loudly in one
test (``tests/transport/coap/test_aiocoap_adapter.py``) instead of quietly
reverting to stock behaviour.

:class:`ContextHooks` installs the hooks per context, never on a class, so
other contexts in the process keep stock behaviour.  The one fix made on a
class, once, at import, is :func:`_uncached_member`: aiocoap's extensible
enums would otherwise keep a member for every unknown value a datagram
names, for the life of the process.

docs/aiocoap.md lists every touch, why it is there, the upstream change
that would remove it, and the call graph the CON hooks rely on.
"""

from __future__ import annotations

import asyncio
import functools
import inspect
import logging
from collections import OrderedDict
from collections.abc import Callable, Mapping
from typing import Any, Protocol

import aiocoap
import aiocoap.meta
from aiocoap.blockwise import Block1Spool, Block2Cache, ContinueException, IncompleteException, _extract_block_key
from aiocoap.messagemanager import MessageManager
from aiocoap.numbers.codes import EMPTY
from aiocoap.numbers.types import CON, NON, RST
from aiocoap.util import ExtensibleIntEnum

from ...errors import CoapkbError
from ..base import TrafficCounters
from . import wire_trace
from .bounds import MESSAGE_OVERHEAD, StateBounds

__all__ = [
    "SUPPORTED_AIOCOAP_VERSION",
    "UnsupportedAiocoapVersion",
    "verify",
    "ConPolicy",
    "ContextHooks",
    "local_port",
    "block_key",
    "extract_block",
    "Block1Spool",
    "Block2Cache",
    "ContinueException",
    "IncompleteException",
]

log = logging.getLogger(__name__)

SUPPORTED_AIOCOAP_VERSION = "0.4.17"

#: Private methods of MessageManager hooked here, with their parameters (without self).
_CON_HOOKS = {
    "_add_exchange": ("message", "messageerror_monitor"),
    "_schedule_retransmit": ("message", "timeout", "retransmission_counter"),
    "_retransmit": ("message", "timeout", "retransmission_counter"),
    "_remove_exchange": ("message",),
}
#: Public methods of MessageManager and the UDP interface wrapped here.
_WRAPPED = {
    (MessageManager, "send_message"): ("message", "messageerror_monitor"),
    (MessageManager, "dispatch_message"): ("message",),
    (MessageManager, "dispatch_error"): ("error", "remote"),
    (MessageManager, "_deduplicate_message"): ("message",),
    (MessageManager, "_process_response"): ("response",),
    (MessageManager, "_send_initially"): ("message", "messageerror_monitor"),
}
_MARKER = "_coapkb_hooks"
#: What aiocoap's ClientObservation.error raises once its observation was cancelled.
_CANCELLED_OBSERVATION = "already cancelled ClientObservation"
#: NON notifications whose Reset is still matched to their observation.
NON_NOTIFICATIONS_KEPT = 256



class _DuplicateMemory(dict[Any, aiocoap.Message | None]):
    """aiocoap's ``_recent_messages`` (request key -> its answer, or None
    while it is being handled), counting the payload bytes of the answers,
    and bounded in size and age by :meth:`forget_past`, with no timer per
    request."""

    answer_bytes = 0

    def __init__(self, entries: Mapping[Any, aiocoap.Message | None]) -> None:
        super().__init__(entries)
        #: When each request came, oldest first, and the token it came with
        #: (a retransmission repeats it).
        self.came: OrderedDict[Any, tuple[float, bytes]] = OrderedDict()

    def copy_of(self, key: Any, token: bytes) -> bool:
        """Whether a request ``key`` (endpoint, Message ID) with ``token`` is a
        copy of one remembered: a new exchange repeats no token."""
        return key in self and self.came.get(key, (0.0, token))[1] == token

    def remember(self, key: Any, now: float, token: bytes) -> None:
        self.came[key] = (now, token)
        self[key] = None

    def drop(self, key: Any) -> None:
        self.came.pop(key, None)
        self.pop(key, None)

    def forget_past(self, bounds: StateBounds, now: float, room_for: int = 0) -> int:
        """Drop the entries past ``bounds`` (``duplicates``,
        ``duplicate_horizon_s``, ``duplicate_answer_bytes``), oldest first,
        leaving room for ``room_for`` more; returns the bytes dropped."""
        before = self.answer_bytes
        horizon = now - bounds.duplicate_horizon_s
        while self.came:
            oldest, (born, _) = next(iter(self.came.items()))
            if (len(self.came) + room_for <= bounds.duplicates and born > horizon
                    and self.answer_bytes <= bounds.duplicate_answer_bytes):
                break
            self.drop(oldest)
        return before - self.answer_bytes

    def __setitem__(self, key: Any, answer: aiocoap.Message | None) -> None:
        if key in self:
            self._forget(self[key])
        self.answer_bytes += MESSAGE_OVERHEAD + (0 if answer is None else len(answer.payload))
        super().__setitem__(key, answer)

    def pop(self, key: Any, *default: Any) -> Any:
        if key in self:
            self._forget(self[key])
        return super().pop(key, *default)

    def _forget(self, answer: aiocoap.Message | None) -> None:
        self.answer_bytes -= MESSAGE_OVERHEAD + (0 if answer is None else len(answer.payload))


class UnsupportedAiocoapVersion(CoapkbError, RuntimeError):
    """The installed aiocoap is not the one these hooks were verified against."""


def check_methods(checks: Mapping[tuple[type, str], tuple[str, ...]]) -> None:
    """Every ``owner.name`` exists and takes these parameters after ``self``;
    raises :class:`UnsupportedAiocoapVersion` naming the first that does not."""
    for (owner, name), params in checks.items():
        method = getattr(owner, name, None)
        if method is None:
            raise UnsupportedAiocoapVersion(f"aiocoap {owner.__name__} has no {name}")
        found = tuple(inspect.signature(method).parameters)[1:]
        if found != params:
            raise UnsupportedAiocoapVersion(f"aiocoap {owner.__name__}.{name}{found} differs from {params}")


def _uncached_member(cls: type[ExtensibleIntEnum], value: int) -> ExtensibleIntEnum:
    """``ExtensibleIntEnum._missing_`` without adding the value to the enum's map."""
    member = int.__new__(cls, value)
    member._value_ = value
    return member


def _install_uncached_members() -> None:
    if "_value2member_map_[value] = new_member" not in inspect.getsource(ExtensibleIntEnum._missing_):
        raise UnsupportedAiocoapVersion("aiocoap's ExtensibleIntEnum no longer caches unknown members as 0.4.17 did")
    ExtensibleIntEnum._missing_ = classmethod(_uncached_member)


def verify() -> None:
    """Check the version pin and every private name this module uses.

    Raises :class:`UnsupportedAiocoapVersion` naming the first mismatch."""
    if aiocoap.meta.version != SUPPORTED_AIOCOAP_VERSION:
        raise UnsupportedAiocoapVersion(
            f"coapkb's aiocoap hooks are verified against aiocoap {SUPPORTED_AIOCOAP_VERSION}, "
            f"found {aiocoap.meta.version}"
        )
    checks: dict[tuple[type, str], tuple[str, ...]] = {(MessageManager, n): p for n, p in _CON_HOOKS.items()}
    checks.update(_WRAPPED)
    from aiocoap.transports.udp6 import MessageInterfaceUDP6

    checks[(MessageInterfaceUDP6, "send")] = ("message",)
    checks[(MessageInterfaceUDP6, "datagram_msg_received")] = ("data", "ancdata", "flags", "address")
    checks[(MessageInterfaceUDP6, "error_received")] = ("exc",)
    checks[(MessageInterfaceUDP6, "_local_port")] = ()
    checks[(aiocoap.Message, "_extract_block")] = ("number", "size_exp", "max_bert_size")
    checks[(aiocoap.Message, "_append_request_block")] = ("next_block",)
    check_methods(checks)
    if tuple(inspect.signature(_extract_block_key).parameters) != ("message",):
        raise UnsupportedAiocoapVersion("aiocoap.blockwise._extract_block_key changed")
    from aiocoap.tokenmanager import TokenManager

    if "self.incoming_requests = None" not in inspect.getsource(TokenManager.shutdown):
        raise UnsupportedAiocoapVersion("aiocoap's token manager no longer marks itself shut down")
    if "self._piggyback_opportunities" not in inspect.getsource(MessageManager.__init__):
        raise UnsupportedAiocoapVersion("aiocoap's MessageManager keeps its empty-ACK timers elsewhere")
    if f'getChild("{BLOCKWISE_LOGGER}")' not in inspect.getsource(aiocoap.protocol.BlockwiseRequest.__init__):
        raise UnsupportedAiocoapVersion("aiocoap's block-wise requester logs elsewhere")
    if _CANCELLED_OBSERVATION not in inspect.getsource(aiocoap.protocol.ClientObservation.error):
        raise UnsupportedAiocoapVersion("aiocoap's cancelled observation raises another error")


# --------------------------------------------------------------------- OSCORE and EDHOC
# coapkb.security's classes subclass aiocoap's OSCORE site and transport and
# its EDHOC contexts (they carry the team's policy, so they live there); the
# private names they rely on are declared and checked here with the rest.


def _oscore_internals() -> dict[tuple[type, str], tuple[str, ...]]:
    from aiocoap import edhoc
    from aiocoap.credentials import CredentialsMap
    from aiocoap.oscore_sitewrapper import OscoreSiteWrapper
    from aiocoap.transports.oscore import TransportOSCORE

    return {
        (OscoreSiteWrapper, "_get_edhoc_identity"): ("origin",),
        (OscoreSiteWrapper, "render_to_pipe"): ("pipe",),
        (OscoreSiteWrapper, "_process_edhoc_msg12"): ("pipe",),
        (OscoreSiteWrapper, "_process_edhoc_msg34"): ("pipe",),
        (edhoc.EdhocResponderContext, "__init__"): ("responder", "c_i", "c_r", "server_credentials", "logger"),
        (OscoreSiteWrapper, "__init__"): ("inner_site", "server_credentials"),
        (TransportOSCORE, "__init__"): ("context", "forward_context"),
        (TransportOSCORE, "request"): ("request",),
        (TransportOSCORE, "_request"): ("request",),
        (edhoc.EdhocInitiatorContext, "__init__"): ("initiator", "c_ours", "c_theirs", "cred_i_mode", "logger"),
        (edhoc.EdhocInitiatorContext, "message_3_to_include"): (),
        (edhoc.EdhocInitiatorContext, "complete_with_message_4"): ("message_4",),
        (CredentialsMap, "find_oscore"): ("unprotected",),
    }


@functools.cache  # once per process: reading aiocoap's source costs 20 ms of CPU each time
def verify_oscore() -> None:
    """Check every OSCORE/EDHOC internal coapkb.security uses, as
    :func:`verify` does for the transport's; raises
    :class:`UnsupportedAiocoapVersion` naming the first mismatch."""
    from aiocoap import edhoc, oscore

    if aiocoap.meta.version != SUPPORTED_AIOCOAP_VERSION:
        raise UnsupportedAiocoapVersion(f"coapkb.security is verified against aiocoap {SUPPORTED_AIOCOAP_VERSION}")
    check_methods(_oscore_internals())
    # The replay check reads this attribute, which EDHOC contexts lack (coapkb.security sets it).
    if "echo_recovery" not in inspect.getsource(oscore.CanUnprotect.unprotect):
        raise UnsupportedAiocoapVersion("aiocoap's OSCORE replay check changed (echo_recovery)")
    # A responder session is half open until message_3 (coapkb.security prunes by it).
    if "self._incomplete = False" not in inspect.getsource(edhoc.EdhocResponderContext):
        raise UnsupportedAiocoapVersion("aiocoap's EDHOC responder no longer marks a session complete")


_PROTECTION_NOTED: set[str] = set()


def note_protection(attribute: str, describe: Callable[[Any], Any]) -> None:
    """Wrap OSCORE's protect and unprotect, on the classes and once per
    process, so that every outer (protected) message carries
    ``describe(its plaintext)`` as ``attribute``: a packet trace then names
    what a ciphertext holds."""
    if attribute in _PROTECTION_NOTED:
        return
    from aiocoap import oscore

    protect, unprotect = oscore.CanProtect.protect, oscore.CanUnprotect.unprotect
    if (tuple(inspect.signature(protect).parameters) != ("self", "message", "request_id", "kid_context")
            or tuple(inspect.signature(unprotect).parameters) != ("self", "protected_message", "request_id")):
        raise UnsupportedAiocoapVersion("aiocoap's OSCORE protect/unprotect changed; plaintexts cannot be noted")

    # functools.wraps: inspection (verify_oscore) sees the originals.
    @functools.wraps(protect)
    def noting_protect(self: Any, message: Any, request_id: Any = None, *, kid_context: Any = True) -> Any:
        outer, request_id = protect(self, message, request_id, kid_context=kid_context)
        setattr(outer, attribute, describe(message))
        return outer, request_id

    @functools.wraps(unprotect)
    def noting_unprotect(self: Any, protected_message: Any, request_id: Any = None) -> Any:
        plain, request_id = unprotect(self, protected_message, request_id)
        setattr(protected_message, attribute, describe(plain))
        return plain, request_id

    oscore.CanProtect.protect = noting_protect
    oscore.CanUnprotect.unprotect = noting_unprotect
    _PROTECTION_NOTED.add(attribute)


# --------------------------------------------------------------------- small accessors


def _message_manager(ctx: aiocoap.Context) -> MessageManager:
    """The UDP MessageManager of a context created with ``transports=["udp6"]``."""
    for ri in ctx.request_interfaces:
        mm = getattr(ri, "token_interface", None)
        if isinstance(mm, MessageManager):
            return mm
    raise ValueError("context has no UDP MessageManager (create it with transports=['udp6'])")


def local_port(ctx: aiocoap.Context) -> int:
    """The UDP port a context's socket is bound to."""
    return int(_message_manager(ctx).message_interface._local_port())


def block_key(request: aiocoap.Message) -> Any:
    """aiocoap's key of a block-wise transfer: remote, code and options but not
    the body and not the Block options."""
    return _extract_block_key(request)


def extract_block(message: aiocoap.Message, number: int, size_exp: int, max_payload: int) -> aiocoap.Message:
    """Block ``number`` (of size ``2**(size_exp+4)``) of a whole response."""
    return message._extract_block(number, size_exp, max_payload)


class _PipeSafeLogger(logging.LoggerAdapter[logging.Logger]):
    """A context's logger that takes aiocoap's ``exception=`` keyword.

    One error it logs is no error here: a request this client abandoned (a
    try the reliability layer no longer waits for) whose OSCORE task then
    meets its cancelled answer raises InvalidStateError, which aiocoap's
    ``Pipe`` logs as "Discarded exception ... added after ... has ended".
    Nobody waits for that request, so it is logged at debug level."""

    def __init__(self, logger: logging.Logger) -> None:
        super().__init__(logger, {})

    def log(self, level: int, msg: Any, *args: Any, **kwargs: Any) -> None:
        if level >= logging.ERROR and isinstance(kwargs.get("exception"), asyncio.InvalidStateError):
            level = logging.DEBUG
        super().log(level, msg, *args, **kwargs)

    def process(self, msg: Any, kwargs: Any) -> tuple[Any, Any]:
        exception = kwargs.pop("exception", None)
        if exception is not None:
            msg = f"{msg}: {exception!r}"
        return msg, kwargs

    def getChild(self, suffix: str) -> Any:
        child = self.logger.getChild(suffix)
        return _BlockwiseRunnerLog(child) if suffix == BLOCKWISE_LOGGER else child


#: The child logger aiocoap 0.4.17's block-wise requester logs to (checked by verify()).
BLOCKWISE_LOGGER = "blockwise-requester"


class _BlockwiseRunnerLog(logging.LoggerAdapter[logging.Logger]):
    """The block-wise requester's logger, without one false alarm.

    When the caller cancels a block-wise request, aiocoap 0.4.17 cancels its
    runner from a done-callback, which runs one loop turn late.  A runner
    whose last block arrived in that turn sets the result of the cancelled
    future and logs the InvalidStateError as an error with a traceback; one
    whose try then failed (a robot's port refused it while its team was
    stopped) logs that its error "neither went to response nor to
    observation".  Nobody waits for either, so both are logged at debug
    level here."""

    def __init__(self, logger: logging.Logger) -> None:
        super().__init__(logger, {})

    def log(self, level: int, msg: Any, *args: Any, **kwargs: Any) -> None:
        if level >= logging.ERROR and (isinstance(kwargs.get("exc_info"), asyncio.InvalidStateError)
                                       or "neither went to response nor to observation" in str(msg)):
            level = logging.DEBUG
        super().log(level, msg, *args, **kwargs)


# --------------------------------------------------------------------- CON retransmission policy


class ConPolicy(Protocol):
    """Decides the retransmission timers of the CON messages a context sends.

    ``on_send`` sees every CON just before its first transmission and returns
    a record to track it by, or None to leave the message to aiocoap's own
    timers.  The other calls receive that record."""

    def on_send(self, message: aiocoap.Message) -> Any | None: ...

    def timeout(self, record: Any, retransmission_counter: int) -> float:
        """Seconds from transmission number ``retransmission_counter`` (0 = the
        first) to the next one, or to the give-up after the last."""
        ...

    def on_retransmit(self, record: Any) -> None: ...

    def on_give_up(self, record: Any, reason: str) -> None:
        """``reason``: ``timeout`` (retransmissions exhausted) or ``error`` (ICMP)."""
        ...

    def on_reply(self, record: Any, message: aiocoap.Message) -> None:
        """The first ACK or RST of the exchange."""
        ...

    def on_duplicate_reply(self, record: Any, message: aiocoap.Message) -> None:
        """A further ACK/RST of a finished exchange: one more copy reached the peer."""
        ...

    def max_retransmit(self, record: Any) -> int: ...


def _dispatch_quietly(mm: MessageManager, dispatch: Callable[[Exception, Any], None],
                      error: Exception, remote: Any) -> None:
    """aiocoap's dispatch of a transport error to the requests to ``remote``,
    without what it raises for those nobody waits for any more."""
    if mm.token_manager.incoming_requests is None:
        # An ICMP error read after the context shut down: nobody to tell.
        log.debug("late error from %s after shutdown: %s", remote, error)
        return
    try:
        dispatch(error, remote)
    except asyncio.InvalidStateError:
        log.debug("late error for an abandoned request to %s: %s", remote, error)
    except RuntimeError as exc:
        # aiocoap tells an observation whose request failed before its
        # first answer, and raises if its caller had already cancelled it
        # (a feeder stopping while a robot dies).
        if _CANCELLED_OBSERVATION not in str(exc):
            raise
        log.debug("late error for a cancelled observation at %s: %s", remote, error)


class ContextHooks:
    """All per-context patches of one aiocoap context, installed once.

    ``ContextHooks.of(ctx, bounds)`` installs them on first use and returns
    the same object afterwards; :meth:`remove` takes every patch off again
    (call it before ``ctx.shutdown()``).  ``bounds`` limits the duplicate
    memory."""

    def __init__(self, ctx: aiocoap.Context, bounds: StateBounds = StateBounds()) -> None:
        self.ctx = ctx
        self.bounds = bounds
        self.mm = _message_manager(ctx)
        self.interface = self.mm.message_interface
        self.counters = TrafficCounters()
        self.con_policy: ConPolicy | None = None
        self._originals: dict[tuple[Any, str], Callable[..., Any]] = {}
        self._instance_attributes: dict[int, set[str]] = {}
        #: (remote, mid) -> policy record, for CON exchanges aiocoap has active.
        self._pending: dict[tuple[Any, int], Any] = {}
        #: Finished exchanges, for the replies to their copies.
        self._finished = _FinishedExchanges()
        #: (remote, Message ID) of the latest NON notifications -> what ends
        #: their observation: aiocoap matches a Reset only to a CON.
        self._non_notifications: OrderedDict[tuple[Any, int], Any] = OrderedDict()
        self._recent_con: OrderedDict[tuple[Any, int], None] = OrderedDict()
        #: Queued notifications dropped because a newer one of the same observation came.
        self.superseded_notifications = 0
        #: Told the size of every datagram this context sends (a link-queue model, say).
        self.on_datagram: Callable[[int], None] | None = None
        #: While a send is under way: the errors its sendmsg raised (else None).
        self._send_errors: list[OSError] | None = None
        #: Every datagram sent, written down (``COAPKB_WIRE_TRACE``), or None.
        self.trace = wire_trace.tracer(note_protection)

    @classmethod
    def of(cls, ctx: aiocoap.Context, bounds: StateBounds = StateBounds()) -> ContextHooks:
        mm = _message_manager(ctx)
        hooks: ContextHooks | None = mm.__dict__.get(_MARKER)
        if hooks is None:
            verify()
            hooks = cls(ctx, bounds)
            hooks._install()
            setattr(mm, _MARKER, hooks)
        return hooks

    def set_con_policy(self, policy: ConPolicy | None) -> None:
        """Route this context's CON timers through ``policy`` (None: aiocoap's)."""
        if policy is not None and self.con_policy is not None and self.con_policy is not policy:
            raise ValueError("this context's CON timers already follow another policy")
        self.con_policy = policy
        if policy is None:
            self._pending.clear()
            self._finished.clear()

    def cancel_empty_ack_timers(self) -> None:
        """Cancel the timers aiocoap keeps to send an empty ACK for a CON
        request whose answer is slow.  Its ``shutdown()`` leaves them running:
        one that fires after the socket closed raised inside an asyncio
        callback (a logged traceback at a robot's SIGTERM after a burst of
        CON requests).  Call before ``ctx.shutdown()``."""
        pending = self.mm._piggyback_opportunities
        for _mid, handle in pending.values():
            handle.cancel()
        pending.clear()

    async def close_socket(self) -> None:
        """Shut the message layer and its socket down, if aiocoap's context
        shutdown stopped before it (an error raised by an observation of
        the token layer above leaves the socket open and read)."""
        if self.mm._active_exchanges is not None:
            await self.mm.shutdown()

    def remove(self) -> None:
        """Take the patches off (after ``ctx.shutdown()``: shutting down is
        when the logger patch matters)."""
        for (owner, name), original in self._originals.items():
            if name in self._instance_attributes.get(id(owner), ()):
                setattr(owner, name, original)
            else:
                owner.__dict__.pop(name, None)
        self._originals.clear()
        self.mm.__dict__.pop(_MARKER, None)
        self.con_policy = None
        # One guard stays on: aiocoap's shutdown can leave its socket open
        # (broken off by an observation's error, or past its 3 s timeout on a
        # busy machine), and an ICMP error read then reached a token manager
        # already gone: a traceback at Ctrl-C.
        if "dispatch_error" not in vars(self.mm):
            self.mm.dispatch_error = functools.partial(_dispatch_quietly, self.mm, self.mm.dispatch_error)

    # ------------------------------------------------------------ installation

    def _patch(self, owner: Any, name: str, replacement: Any) -> None:
        if name in vars(owner):  # an attribute of the instance itself: restore it, not the class's
            self._instance_attributes.setdefault(id(owner), set()).add(name)
        self._originals[(owner, name)] = getattr(owner, name)
        setattr(owner, name, replacement)

    def _install(self) -> None:
        self.mm._recent_messages = _DuplicateMemory(self.mm._recent_messages)
        if not isinstance(self.ctx.log, _PipeSafeLogger):
            self._patch(self.ctx, "log", _PipeSafeLogger(self.ctx.log))
        self._patch(self.interface, "send", self._send)
        self._patch(self.interface, "datagram_msg_received", self._datagram_received)
        self._patch(self.interface, "error_received", self._error_received)
        self._patch(self.mm, "send_message", self._send_message)
        self._patch(self.mm, "dispatch_message", self._dispatch_message)
        self._patch(self.mm, "dispatch_error", self._dispatch_error)
        self._patch(self.mm, "_deduplicate_message", self._deduplicate_message)
        self._patch(self.mm, "_process_response", self._process_response)
        self._patch(self.mm, "_add_exchange", self._add_exchange)
        self._patch(self.mm, "_schedule_retransmit", self._schedule_retransmit)
        self._patch(self.mm, "_retransmit", self._retransmit)
        self._patch(self.mm, "_remove_exchange", self._remove_exchange)

    def _original(self, owner: Any, name: str) -> Callable[..., Any]:
        return self._originals[(owner, name)]

    # ------------------------------------------------------------ socket: counters

    def _send(self, message: aiocoap.Message) -> None:
        send = self._original(self.interface, "send")
        errors: list[OSError] = []
        self._send_errors = errors
        try:
            send(message)
            if errors:  # most likely another peer's stale ICMP error, now cleared: once more
                log.debug("send to %s failed (%s); sending again", message.remote, errors[-1])
                errors.clear()
                send(message)
        finally:
            self._send_errors = None
        if errors:  # failed twice: the destination's own (no route, say), as aiocoap would report it
            self.mm.dispatch_error(errors[-1], message.remote)
            return
        counters = self.counters
        data = message.encode()
        size = len(data)
        if self.trace is not None:
            self.trace.sent("client" if self.ctx.serversite is None else "server", local_port(self.ctx), message, data)
        counters.messages_sent += 1
        counters.bytes_sent += size
        if self.on_datagram is not None:
            self.on_datagram(size)
        repeat = False
        if message.mtype == CON:
            key = (message.remote.sockaddr, message.mid)
            if key in self._recent_con:
                counters.retransmissions += 1
                repeat = True
            else:
                self._recent_con[key] = None
                if len(self._recent_con) > 4096:
                    self._recent_con.popitem(last=False)
        if not repeat and message.code.is_response() and message.opt.observe is not None:
            counters.notifications_sent += 1

    def _error_received(self, exc: OSError) -> None:
        if self._send_errors is not None:  # raised by our sendmsg: _send decides
            self._send_errors.append(exc)
        else:
            self._original(self.interface, "error_received")(exc)

    def _datagram_received(self, data: bytes, ancdata: Any, flags: int, address: Any) -> None:
        self.counters.messages_received += 1
        self.counters.bytes_received += len(data)
        try:
            self._original(self.interface, "datagram_msg_received")(data, ancdata, flags, address)
        except UnicodeDecodeError:
            log.debug("dropped a datagram from %s: string option is not UTF-8", address)

    # ------------------------------------------------------------ notifications

    def _send_message(self, message: aiocoap.Message, messageerror_monitor: Any = None) -> Any:
        result = self._original(self.mm, "send_message")(message, messageerror_monitor)
        if message.opt.observe is not None and message.code.is_response():
            if message.mtype == NON and messageerror_monitor is not None and message.mid is not None:
                self._non_notifications[(message.remote, message.mid)] = messageerror_monitor
                while len(self._non_notifications) > NON_NOTIFICATIONS_KEPT:
                    self._non_notifications.popitem(last=False)
            backlog = self.mm._backlogs.get(message.remote)
            if backlog and backlog[-1][0] is message:
                superseded = [entry for entry in backlog[:-1]
                              if entry[0].token == message.token and entry[0].opt.observe is not None]
                for entry in superseded:
                    backlog.remove(entry)
                self.superseded_notifications += len(superseded)
        return result

    # ------------------------------------------------------------ duplicates

    def _deduplicate_message(self, message: aiocoap.Message) -> bool:
        """aiocoap's duplicate detection, with its memory bounded (:class:`_DuplicateMemory`)."""
        recent: _DuplicateMemory = self.mm._recent_messages
        key = (message.remote, message.mid)
        if recent.copy_of(key, message.token):
            return bool(self._original(self.mm, "_deduplicate_message")(message))
        # Same endpoint and Message ID, another token: not a copy but a new
        # exchange of a client that started again on the same port (a
        # restarted robot; each run of coap-client -p) and cannot know its
        # predecessor's IDs.  Answering it the old exchange's stored answer
        # would hand it another request's answer.
        recent.drop(key)
        recent.forget_past(self.bounds, self.mm.loop.time(), room_for=1)
        recent.remember(key, self.mm.loop.time(), message.token)
        return False

    def forget_duplicates(self) -> int:
        """Drop the duplicate memory's entries past :attr:`bounds`; returns the bytes dropped."""
        memory: _DuplicateMemory = self.mm._recent_messages
        return memory.forget_past(self.bounds, self.mm.loop.time())

    # ------------------------------------------------------------ late events

    def _dispatch_message(self, message: aiocoap.Message) -> None:
        try:
            self._original(self.mm, "dispatch_message")(message)
        except asyncio.InvalidStateError:
            log.debug("late response from %s for an abandoned request", message.remote)

    def _process_response(self, response: aiocoap.Message) -> bool:
        """aiocoap rejects an unexpected CON response with a Reset, and
        ignores an unexpected NON one.  A NON notification of an observation
        this client gave up (it registered again) is rejected too, as RFC 7641
        §3.6 lets a client do: notifications go NON, and the server would
        otherwise send each state twice until its next CON one."""
        expected = bool(self._original(self.mm, "_process_response")(response))
        if not expected and response.mtype == NON and response.opt.observe is not None \
                and not response.remote.is_multicast_locally:
            rst = aiocoap.Message(_mtype=RST, _mid=response.mid, code=EMPTY, payload=b"")
            rst.remote = response.remote.as_response_address()
            self.mm._send_initially(rst)
        return expected

    def _dispatch_error(self, error: Exception, remote: Any) -> None:
        if self.con_policy is not None and self.mm.token_manager.incoming_requests is not None:
            for key in [k for k in self._pending if k[0] == remote]:
                self.con_policy.on_give_up(self._pending.pop(key), "error")
        _dispatch_quietly(self.mm, self._original(self.mm, "dispatch_error"), error, remote)

    # ------------------------------------------------------------ CON timers

    def _add_exchange(self, message: aiocoap.Message, messageerror_monitor: Callable[[], None]) -> None:
        if self.con_policy is not None:
            record = self.con_policy.on_send(message)
            if record is not None:
                self._pending[(message.remote, message.mid)] = record
        self._original(self.mm, "_add_exchange")(message, messageerror_monitor)

    def _schedule_retransmit(self, message: aiocoap.Message, timeout: float, retransmission_counter: int) -> Any:
        record = self._pending.get((message.remote, message.mid))
        if record is not None and self.con_policy is not None:
            timeout = self.con_policy.timeout(record, retransmission_counter)
        return self._original(self.mm, "_schedule_retransmit")(message, timeout, retransmission_counter)

    def _retransmit(self, message: aiocoap.Message, timeout: float, retransmission_counter: int) -> None:
        key = (message.remote, message.mid)
        record = self._pending.get(key)
        if record is not None and self.con_policy is not None:
            if retransmission_counter >= message.transport_tuning.MAX_RETRANSMIT:
                self._pending.pop(key, None)
                self.con_policy.on_give_up(record, "timeout")
            else:
                self.con_policy.on_retransmit(record)
        self._original(self.mm, "_retransmit")(message, timeout, retransmission_counter)

    def _remove_exchange(self, message: aiocoap.Message) -> None:
        key = (message.remote, message.mid)
        policy = self.con_policy
        if policy is not None:
            now = self.mm.loop.time()
            record = self._pending.pop(key, None)
            if record is not None:
                policy.on_reply(record, message)
                self._finished.remember(key, record, now)
            else:
                finished = self._finished.get(key, now)
                if finished is not None:
                    policy.on_duplicate_reply(finished, message)
        ended = self._non_notifications.pop(key, None)
        if ended is not None and message.mtype == RST and key not in self.mm._active_exchanges:
            ended()  # a NON notification reset: its observer is gone (RFC 7641 §3.6)
            return
        self._original(self.mm, "_remove_exchange")(message)



class _FinishedExchanges:
    """CON exchanges that ended, by (remote, Message ID), each with its
    policy record: a reply to a copy sent before the end still tells the
    policy of it.  Such a reply comes within about one RTT; a few seconds
    is ample, and 1024 entries bound memory."""

    HORIZON_S = 5.0
    ENTRIES = 1024

    def __init__(self) -> None:
        self._records: OrderedDict[tuple[Any, int], tuple[Any, float]] = OrderedDict()

    def remember(self, key: tuple[Any, int], record: Any, now: float) -> None:
        self._purge(now)
        self._records[key] = (record, now + self.HORIZON_S)
        while len(self._records) > self.ENTRIES:
            self._records.popitem(last=False)

    def clear(self) -> None:
        self._records.clear()

    def get(self, key: tuple[Any, int], now: float) -> Any | None:
        """The record of the exchange ``key`` that ended lately, or None."""
        self._purge(now)
        entry = self._records.get(key)
        return None if entry is None else entry[0]

    def _purge(self, now: float) -> None:
        while self._records:
            _, (_, expiry) = next(iter(self._records.items()))
            if expiry > now:
                break
            self._records.popitem(last=False)


_install_uncached_members()
