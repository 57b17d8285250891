"""Per-peer retransmission control for aiocoap 0.4.17 (CON requests over UDP).

aiocoap has no RTT estimation.  Its timers come from the message's
``transport_tuning``, and the backoff factor of 2 is hard-coded.  This module
adds what :mod:`coapkb.transport.coap.reliability.rto` needs, without touching aiocoap's classes:

* :meth:`RetransmissionController.tuning_for` returns a :class:`PeerTuning`
  (a ``TransportTuning``) that marks a request as belonging to a peer.  Put it
  on the ``aiocoap.Message``.
* :class:`RetransmissionController` is a
  :class:`~coapkb.transport.coap.aiocoap_adapter.ConPolicy`: the adapter
  calls it just before a CON's first transmission (so the RTO used is the
  one current when the datagram really leaves, after any NSTART backlog
  wait), for every retransmission timeout (replacing aiocoap's hard-coded
  doubling with the profile's schedule: CoCoA's dithering and variable
  backoff, or ``lossy-fixed``'s capped backoff), on each retransmission and
  give-up, and on the first and any duplicate ACK/RST.  The hooks
  themselves, and the aiocoap version pin, live in the adapter.

**Spurious retransmissions** are detected in two ways.  Both give lower
bounds on the count, and we take the larger:

1. *Timing* (Eifel-like, :func:`coapkb.transport.coap.reliability.rto.attribute_reply`).  A reply that
   arrives sooner after a retransmission than half the peer's minimum
   observed RTT cannot be the answer to that retransmission.  Every
   transmission after the latest one the reply can answer was therefore
   unneeded.  If that latest one is the original, the sample is unambiguous
   and is fed to the estimator as **strong**.  This is the Eifel response: a
   delay spike that outran the timer raises the RTO at strong weight instead
   of the weak sample's 0.25.
2. *Duplicate ACKs*.  Each further ACK/RST with an exchange's (remote, MID)
   means the server received one more copy, so at least ``acks − 1``
   transmissions were redundant.  aiocoap (like libcoap) re-sends its stored
   reply for a duplicate CON.  A server still busy with the request sends
   nothing, so this count is only a lower bound.  A network that duplicates
   datagrams would inflate it; ours do not.  Duplicate ACKs only update
   counters.  By the time they arrive the sample has been taken.

**NSTART.**  aiocoap queues CONs to a remote while one is in flight (NSTART=1),
so CoCoA's "blind" multiplier (outstanding exchanges before the first sample)
is always 1 here.  It is still computed, from this controller's pending
exchanges to the peer, in case that changes.
"""

from __future__ import annotations

import logging
import random
import time
from collections import deque
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Callable, Hashable

import aiocoap
import aiocoap.meta
from aiocoap.numbers.constants import TransportTuning
from aiocoap.numbers.types import RST

from ..aiocoap_adapter import ContextHooks
from .rto import (
    DEFAULT_REPLY_BYTES,
    AdaptiveProfile,
    CocoaRto,
    RetransmissionSchedule,
    SampleKind,
    TransmissionProfile,
    attribute_reply,
    classify_sample,
    get_profile,
)

__all__ = [
    "PeerTuning",
    "ExchangeRecord",
    "PeerStats",
    "RetransmissionController",
]

log = logging.getLogger(__name__)


#: Reply size assumed for a non-final Block1 request: its reply is a small
#: 2.31 Continue (header, token, Block1 option).
SMALL_REPLY_BYTES = 32

#: Strong samples needed before a peer's minimum RTT is used as evidence
#: that a reply answered an earlier copy (see the module docstring).
MIN_SAMPLES_FOR_ATTRIBUTION = 3

def _ip_udp_overhead(remote: Any) -> int:
    """IP+UDP header bytes per datagram to ``remote``: 28 for IPv4 (aiocoap's
    udp6 transport shows these as ``::ffff:a.b.c.d``), 48 for IPv6."""
    sockaddr = getattr(remote, "sockaddr", None)
    if sockaddr and isinstance(sockaddr[0], str) and (sockaddr[0].startswith("::ffff:") or "." in sockaddr[0]):
        return 28
    return 48


def _encoded_len(message: aiocoap.Message) -> int:
    try:
        return len(message.encode())
    except Exception:  # an unencodable message would not have been sent; be robust anyway
        return len(message.payload) + 16


class PeerTuning(TransportTuning):  # type: ignore[misc]  # aiocoap ships no type information
    """The ``transport_tuning`` of a request handled by a
    :class:`RetransmissionController`.

    It carries the peer key and the reply size to expect.  Its
    ``ACK_TIMEOUT``/``ACK_RANDOM_FACTOR``/``MAX_RETRANSMIT`` are set per
    instance from the profile (for ``adaptive``, from the peer's current RTO),
    so that code reading them, and aiocoap itself if the hooks are *not*
    installed on the sending context, sees sensible values.  Without the hooks aiocoap falls back to
    ``uniform(ACK_TIMEOUT, ACK_TIMEOUT·ACK_RANDOM_FACTOR)`` doubling up to
    ``MAX_RETRANSMIT``.

    aiocoap copies ``transport_tuning`` into the follow-up block requests it
    generates, so every block exchange of a block-wise transfer is measured
    for the same peer.
    """

    def __init__(
        self,
        controller: "RetransmissionController",
        peer_key: Hashable,
        *,
        ack_timeout: float,
        ack_random_factor: float,
        max_retransmit: int,
        max_transmit_wait: float,
        expected_reply_bytes: int | None,
        reliability: bool | None,
    ) -> None:
        self.controller = controller
        self.peer_key = peer_key
        self.expected_reply_bytes = expected_reply_bytes
        self.ACK_TIMEOUT = ack_timeout
        self.ACK_RANDOM_FACTOR = ack_random_factor
        self.MAX_RETRANSMIT = max_retransmit
        self._max_transmit_wait = max_transmit_wait
        self.reliability = reliability

    @property
    def MAX_TRANSMIT_WAIT(self) -> float:
        """The profile's bound (with the hooks installed), not RFC 7252's formula."""
        return self._max_transmit_wait

    def __repr__(self) -> str:
        return f"<PeerTuning {self.peer_key!r} via {self.controller.profile.name}>"


@dataclass
class ExchangeRecord:
    """One CON exchange as the controller saw it (kept in a short per-peer
    history for debugging and tests)."""

    peer_key: Hashable
    mid: int
    schedule: RetransmissionSchedule
    request_bytes: int
    expected_reply_bytes: int
    transmit_times: list[float] = field(default_factory=list)
    reply_time: float | None = None
    reply_bytes: int | None = None
    replies: int = 0
    outcome: str = "pending"  # pending | ack | rst | timeout | error
    rtt: float | None = None
    sample: SampleKind | None = None
    spurious: int = 0

    @property
    def retransmissions(self) -> int:
        return max(0, len(self.transmit_times) - 1)

    @property
    def gaps(self) -> list[float]:
        """Measured time between consecutive transmissions (compare with
        ``schedule.timeout(n)``)."""
        t = self.transmit_times
        return [b - a for a, b in zip(t, t[1:])]

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["peer_key"] = str(self.peer_key)
        d["sample"] = None if self.sample is None else self.sample.value
        d["retransmissions"] = self.retransmissions
        return d


@dataclass
class PeerStats:
    """Counters for one peer: what the agent records per run."""

    exchanges: int = 0
    acked: int = 0
    reset: int = 0
    failed: int = 0
    transmissions: int = 0
    retransmissions: int = 0
    samples_strong: int = 0
    samples_weak: int = 0
    samples_discarded: int = 0
    reattributed_strong: int = 0
    """Samples with retransmissions that timing proved unambiguous (fed as strong)."""
    spurious_retransmissions: int = 0
    duplicate_replies: int = 0
    last_rtt: float | None = None
    last_initial_timeout: float | None = None
    rto: float | None = None
    min_rtt: float | None = None
    srtt: float | None = None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class _PeerState:
    def __init__(self, rto: CocoaRto) -> None:
        self.rto = rto
        self.stats = PeerStats()
        self.history: deque[ExchangeRecord] = deque()


class RetransmissionController:
    """Per-peer retransmission timeouts for CoAP CON requests sent by aiocoap.

    One controller holds one :class:`~coapkb.transport.coap.reliability.rto.TransmissionProfile` and a
    :class:`~coapkb.transport.coap.reliability.rto.CocoaRto` per peer key.  A peer key is anything
    hashable that identifies a peer, for example the transport's
    ``Endpoint``.  Use it like this::

        controller = RetransmissionController("adaptive", rng=random.Random(seed))
        ctx = await aiocoap.Context.create_client_context(transports=["udp6"])
        controller.install(ctx)                       # once per context
        msg = aiocoap.Message(..., transport_tuning=controller.tuning_for(peer))
        bound = controller.max_transmit_wait(peer)    # per-exchange bound, s

    All three profiles go through the hooks, so the fixed ones get exactly
    their schedule (``lossy-fixed``'s 8 s cap included) and all of them
    collect the same per-peer statistics.  State is per instance; there are no
    globals.
    """

    def __init__(
        self,
        profile: TransmissionProfile | str = "adaptive",
        *,
        rng: random.Random | None = None,
        clock: Callable[[], float] = time.monotonic,
        history: int = 64,
        spurious_rtt_fraction: float = 0.5,
    ) -> None:
        """``clock`` must be the clock of the event loop the contexts run on.
        asyncio's default loops use ``time.monotonic``.  ``history`` is how
        many finished exchanges to keep per peer.  ``spurious_rtt_fraction``
        is the share of the minimum RTT a reply must arrive within, after a
        retransmission, to be credited to an earlier copy."""
        self.profile = get_profile(profile)
        self.rng = rng if rng is not None else random.Random()
        self.clock = clock
        self.history = history
        self.spurious_rtt_fraction = spurious_rtt_fraction
        self._peers: dict[Hashable, _PeerState] = {}
        #: CON exchanges sent and not yet finished, per peer (CoCoA's "blind" multiplier).
        self._outstanding: dict[Hashable, int] = {}

    # ------------------------------------------------------------ public API

    def tuning_for(
        self,
        peer_key: Hashable,
        *,
        expected_reply_bytes: int | None = None,
        reliability: bool | None = True,
    ) -> PeerTuning:
        """The ``transport_tuning`` for a request to ``peer_key``.  Create one
        per request; it is cheap.

        ``expected_reply_bytes`` is the CoAP size of the reply if the caller
        knows it.  It only matters for the adaptive profile with a link rate.
        The default assumes a full block (:data:`~coapkb.transport.coap.reliability.rto.DEFAULT_REPLY_BYTES`),
        or a small 2.31 Continue for non-final Block1 requests.
        ``reliability=True`` makes aiocoap send CON.  Only CON requests are
        retransmitted, and so only they are handled here."""
        state = self._peer(peer_key)
        now = self.clock()
        if isinstance(self.profile, AdaptiveProfile):
            low, _ = state.rto.initial_timeout_range(now)
            ack_timeout, factor = low, self.profile.dither
            bound = self.profile.max_transmit_wait_for(state.rto, now, self._wire_bytes(None, expected_reply_bytes))
        else:
            ack_timeout = self.profile.ack_timeout  # type: ignore[attr-defined]
            factor = self.profile.ack_random_factor  # type: ignore[attr-defined]
            bound = self.profile.max_transmit_wait()
        return PeerTuning(
            self,
            peer_key,
            ack_timeout=ack_timeout,
            ack_random_factor=factor,
            max_retransmit=self.profile.max_retransmit,
            max_transmit_wait=bound,
            expected_reply_bytes=expected_reply_bytes,
            reliability=reliability,
        )

    def max_transmit_wait(self, peer_key: Hashable, *, expected_reply_bytes: int | None = None) -> float:
        """Upper bound (s) on one exchange to ``peer_key`` started now, from
        its first transmission to the give-up.

        A request's total time adds any NSTART backlog wait, and a block-wise
        transfer adds one exchange per block.  Callers should size their
        ``asyncio.timeout`` for that."""
        if isinstance(self.profile, AdaptiveProfile):
            state = self._peer(peer_key)
            wire = self._wire_bytes(None, expected_reply_bytes)
            return self.profile.max_transmit_wait_for(state.rto, self.clock(), wire)
        return self.profile.max_transmit_wait()

    def install(self, context: aiocoap.Context) -> None:
        """Route the CON timers of ``context`` through this controller (call
        once, right after creating it; again is a no-op).

        Raises the adapter's ``UnsupportedAiocoapVersion`` if aiocoap is not the
        verified version, and ``ValueError`` if the context has no UDP
        message manager or another policy already drives its timers."""
        ContextHooks.of(context).set_con_policy(self)

    def uninstall(self, context: aiocoap.Context) -> None:
        """Give ``context``'s CON timers back to aiocoap.  An exchange in
        flight keeps the timer already scheduled and is no longer measured."""
        hooks = ContextHooks.of(context)
        if hooks.con_policy is self:
            hooks.set_con_policy(None)

    # ------------------------------------------------------------ ConPolicy

    def on_send(self, message: aiocoap.Message) -> ExchangeRecord | None:
        tuning = message.transport_tuning
        if isinstance(tuning, PeerTuning) and tuning.controller is self:
            return self._start_exchange(message, tuning)
        return None

    def timeout(self, record: ExchangeRecord, retransmission_counter: int) -> float:
        return record.schedule.timeout(retransmission_counter)

    def on_retransmit(self, record: ExchangeRecord) -> None:
        record.transmit_times.append(self.clock())
        self._count_retransmission(record)

    def on_give_up(self, record: ExchangeRecord, reason: str) -> None:
        self._finish_failed(record, reason)

    def on_reply(self, record: ExchangeRecord, message: aiocoap.Message) -> None:
        self._finish_replied(record, message, self.clock())

    def on_duplicate_reply(self, record: ExchangeRecord, message: aiocoap.Message) -> None:
        self._duplicate_reply(record)

    def max_retransmit(self, record: ExchangeRecord) -> int:
        return self.profile.max_retransmit

    def rto(self, peer_key: Hashable) -> float:
        """The peer's current overall RTO (s), aged to now."""
        return self._peer(peer_key).rto.rto(self.clock())

    def estimator(self, peer_key: Hashable) -> CocoaRto:
        """The peer's live estimator state (read-only use, please)."""
        return self._peer(peer_key).rto

    def stats(self, peer_key: Hashable) -> PeerStats:
        """A snapshot of the peer's counters and current RTO."""
        state = self._peer(peer_key)
        now = self.clock()
        return replace(
            state.stats,
            rto=state.rto.rto(now),
            min_rtt=state.rto.min_rtt,
            srtt=state.rto.strong.srtt,
        )

    def peers(self) -> list[Hashable]:
        return list(self._peers)

    def recent_exchanges(self, peer_key: Hashable) -> list[ExchangeRecord]:
        """The last ``history`` finished exchanges to the peer, oldest first."""
        return list(self._peer(peer_key).history)

    def as_dict(self) -> dict[str, Any]:
        """Profile and per-peer statistics, for the agent's record."""
        return {
            "profile": self.profile.as_dict(),
            "peers": {str(k): self.stats(k).as_dict() for k in self._peers},
        }

    # ------------------------------------------------------------ internals

    def _peer(self, peer_key: Hashable) -> _PeerState:
        state = self._peers.get(peer_key)
        if state is None:
            state = self._peers[peer_key] = _PeerState(self.profile.new_rto())
        return state

    @staticmethod
    def _wire_bytes(message: aiocoap.Message | None, expected_reply_bytes: int | None, overhead: int = 28) -> int:
        """Link bytes of a whole exchange: request datagram plus expected reply."""
        request = _encoded_len(message) if message is not None else 64
        reply = DEFAULT_REPLY_BYTES if expected_reply_bytes is None else expected_reply_bytes
        return request + reply + 2 * overhead

    def _start_exchange(self, message: aiocoap.Message, tuning: PeerTuning) -> ExchangeRecord:
        state = self._peer(tuning.peer_key)
        now = self.clock()
        overhead = _ip_udp_overhead(message.remote)
        request_bytes = _encoded_len(message)
        if tuning.expected_reply_bytes is not None:
            reply_bytes = tuning.expected_reply_bytes
        elif message.opt.block1 is not None and message.opt.block1.more:
            reply_bytes = SMALL_REPLY_BYTES
        else:
            reply_bytes = DEFAULT_REPLY_BYTES
        outstanding = self._outstanding.get(tuning.peer_key, 0) + 1
        self._outstanding[tuning.peer_key] = outstanding
        schedule = self.profile.schedule(
            self.rng,
            state.rto,
            now,
            wire_bytes=request_bytes + reply_bytes + 2 * overhead,
            outstanding=outstanding,
        )
        record = ExchangeRecord(
            peer_key=tuning.peer_key,
            mid=message.mid,
            schedule=schedule,
            request_bytes=request_bytes,
            expected_reply_bytes=reply_bytes,
            transmit_times=[now],
        )
        state.stats.exchanges += 1
        state.stats.transmissions += 1
        state.stats.last_initial_timeout = schedule.initial_timeout
        log.debug(
            "exchange %s mid=%d to %r: timeouts %s", self.profile.name, message.mid, tuning.peer_key,
            ", ".join(f"{t:.3f}" for t in schedule.timeouts()),
        )
        return record

    def _count_retransmission(self, record: ExchangeRecord) -> None:
        stats = self._peer(record.peer_key).stats
        stats.transmissions += 1
        stats.retransmissions += 1

    def _finish_replied(self, record: ExchangeRecord, reply: aiocoap.Message, now: float) -> None:
        state = self._peer(record.peer_key)
        stats = state.stats
        record.reply_time = now
        record.reply_bytes = _encoded_len(reply)
        record.replies = 1
        record.outcome = "rst" if reply.mtype is RST else "ack"
        record.rtt = now - record.transmit_times[0]
        if reply.mtype is RST:
            stats.reset += 1
        else:
            stats.acked += 1
        stats.last_rtt = record.rtt

        kind = classify_sample(record.retransmissions)
        if record.retransmissions:
            # Timing evidence needs a trustworthy minimum RTT: one or two
            # samples may all have been slow ones.
            min_rtt = state.rto.min_rtt if state.rto.strong.samples >= MIN_SAMPLES_FOR_ATTRIBUTION else None
            index = attribute_reply(record.transmit_times, now, min_rtt, self.spurious_rtt_fraction)
            record.spurious = record.retransmissions - index
            stats.spurious_retransmissions += record.spurious
            if index == 0:
                kind = SampleKind.STRONG
                stats.reattributed_strong += 1
        overhead = _ip_udp_overhead(reply.remote)
        state.rto.on_sample(
            record.rtt,
            record.retransmissions,
            now,
            wire_bytes=record.request_bytes + record.reply_bytes + 2 * overhead,
            kind=kind,
        )
        record.sample = kind
        if kind is SampleKind.STRONG:
            stats.samples_strong += 1
        elif kind is SampleKind.WEAK:
            stats.samples_weak += 1
        else:
            stats.samples_discarded += 1
        self._archive(state, record)

    def _duplicate_reply(self, record: ExchangeRecord) -> None:
        stats = self._peer(record.peer_key).stats
        stats.duplicate_replies += 1
        record.replies += 1
        # n replies prove n copies reached the server: n-1 were redundant.
        proven = min(record.replies - 1, record.retransmissions)
        if proven > record.spurious:
            stats.spurious_retransmissions += proven - record.spurious
            record.spurious = proven

    def _finish_failed(self, record: ExchangeRecord, outcome: str) -> None:
        state = self._peer(record.peer_key)
        record.outcome = outcome
        state.stats.failed += 1
        self._archive(state, record)

    def _archive(self, state: _PeerState, record: ExchangeRecord) -> None:
        self._outstanding[record.peer_key] = max(0, self._outstanding.get(record.peer_key, 1) - 1)
        state.history.append(record)
        while len(state.history) > self.history:
            state.history.popleft()
