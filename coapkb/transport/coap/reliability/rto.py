"""Retransmission timeouts for CoAP over slow, lossy links: CoCoA-style RTO
estimation and the three transmission profiles coapkb can run with.

Everything here is pure: no I/O, no asyncio, no clocks.  Times are plain
floats in seconds, passed in by the caller (``now``), and randomness comes
from a ``random.Random`` the caller owns, so the arithmetic can be unit-tested
exactly and replayed.  :mod:`coapkb.transport.coap.reliability.cocoa_hooks` wires it into aiocoap.

Why: RFC 7252's fixed timers (ACK_TIMEOUT 2 s, dithered to 2-3 s, doubling)
make every lost datagram cost 2-3 s, while a fixed *short* timeout fires
spuriously when a 1 KB answer needs 234 ms just to be serialised onto a
35 kbit/s link.  CoCoA (draft-ietf-core-cocoa-03, also in Californium) instead
estimates a per-peer RTO from measured round trips.  This module implements
CoCoA as specified with one documented extension, *size normalisation*:

* **Size normalisation** (coapkb's own choice, off unless the link rate is
  known).  On a 35 kbit/s link most of a round trip can be serialisation:
  8·bytes/rate for the request plus the reply.  Fed raw, a mix of 40-byte
  and 1100-byte exchanges makes RTTVAR large (timeouts too long for the small
  ones) and still lets a run of small exchanges pull the RTO below what the
  next full block needs.  When ``link_rate_bps`` is given, every sample has
  the serialisation time of *its own* datagrams subtracted before it reaches
  the estimators, so they track the size-independent part (propagation, MAC
  access, queueing, processing).  Each new exchange's timeout then adds the
  serialisation time of *its* request plus the reply it can expect (by
  default a full 1 KB block).  Serialisation at a known rate is deterministic,
  so adding it after dithering does not weaken the variance margin.
* **Lower clamp.**  The dithered initial timeout is clamped to [0.5 s, 60 s]
  as CoCoA specifies.  On these links that floor sits at about twice the worst
  single-exchange round trip we expect (a full block each way at 35 kbit/s is
  about 0.52 s plus propagation, and a typical exchange about 0.3 s), so it
  seldom binds.  On loopback or Ethernet it is far above the true RTT, and we
  keep it there deliberately.  A timeout shorter than 0.5 s would speed up
  recovery from a loss by at most 0.5 s.  Below that, any delay spike on a
  shared radio channel causes a spurious retransmission, and each one costs
  real airtime (234 ms for a 1 KB block at 35 kbit/s).  The floor is a
  parameter (``min_timeout``) for lab use, not something to tune in the field.
"""

from __future__ import annotations

import abc
import enum
import math
import random
from dataclasses import asdict, dataclass, field, replace
from typing import Any, ClassVar, Sequence

__all__ = [
    "RFC6298_ALPHA",
    "RFC6298_BETA",
    "CLOCK_GRANULARITY",
    "DEFAULT_REPLY_BYTES",
    "SampleKind",
    "classify_sample",
    "variable_backoff_factor",
    "worst_case_wait",
    "backed_off_cap",
    "RttEstimator",
    "CocoaRto",
    "attribute_reply",
    "RetransmissionSchedule",
    "TransmissionProfile",
    "FixedProfile",
    "AdaptiveProfile",
    "PROFILES",
    "get_profile",
]

RFC6298_ALPHA = 1 / 8
"""Gain for SRTT (RFC 6298).  Californium swaps α and β; we follow the RFC
and the Contiki CoCoA code."""

RFC6298_BETA = 1 / 4
"""Gain for RTTVAR (RFC 6298)."""

CLOCK_GRANULARITY = 0.1
"""G in ``E = SRTT + max(G, K·RTTVAR)``: CoCoA's 100 ms floor for the
variance margin, so that a perfectly steady RTT still leaves headroom."""

DEFAULT_REPLY_BYTES = 1100
"""CoAP size we assume for a reply whose size is not known in advance: one
full 1024-byte block plus up to 76 bytes of header, token and options.  This
is the largest reply one exchange carries (aiocoap's blocks are at most 1024
bytes on UDP), so a timeout built from it never fires before a full block
could have been serialised."""


class SampleKind(enum.Enum):
    """How much an RTT sample can be trusted (CoCoA §4.2)."""

    STRONG = "strong"
    """The reply answered the only transmission: the RTT is unambiguous."""
    WEAK = "weak"
    """1–2 retransmissions: measured from the first transmission, so the
    sample is an upper bound that also includes timeouts."""
    DISCARDED = "discarded"
    """3 or more retransmissions: too ambiguous to use."""


def classify_sample(retransmissions: int) -> SampleKind:
    """CoCoA's rule: 0 retransmissions → strong, 1–2 → weak, ≥3 → discarded."""
    if retransmissions < 0:
        raise ValueError("retransmissions must be >= 0")
    if retransmissions == 0:
        return SampleKind.STRONG
    if retransmissions <= 2:
        return SampleKind.WEAK
    return SampleKind.DISCARDED


def variable_backoff_factor(initial_timeout: float) -> float:
    """CoCoA's variable backoff factor (VBF) for one exchange.

    When the initial timeout is short (< 1 s) the RTO may be too aggressive,
    so the exchange backs off fast (×3).  When it is long (> 3 s) the path is
    already known to be slow, so a gentler ×1.5 avoids waiting minutes.
    Otherwise ×2, as in RFC 7252."""
    if initial_timeout < 1.0:
        return 3.0
    if initial_timeout > 3.0:
        return 1.5
    return 2.0


def _schedule_total(initial: float, factor: float, max_retransmit: int, cap: float) -> float:
    return sum(min(initial * factor**n, cap) for n in range(max_retransmit + 1))


def backed_off_cap(initial: float, max_timeout: float, backoff_cap: float | None) -> float:
    """The largest timeout an exchange whose initial timeout is ``initial``
    may back off to: ``max_timeout``, or with a ``backoff_cap``
    ``min(max_timeout, max(backoff_cap, initial))``.  The cap limits the
    backoff only; it never shortens an initial timeout the RTO asked for."""
    if backoff_cap is None:
        return max_timeout
    return min(max_timeout, max(backoff_cap, initial))


def worst_case_wait(
    low: float,
    high: float,
    max_retransmit: int,
    max_timeout: float,
    backoff_factor: float | None = None,
    backoff_cap: float | None = None,
) -> float:
    """Supremum of the total wait (first transmission → give-up) over every
    initial timeout in ``[low, high]``.

    With a fixed ``backoff_factor`` the total grows with the initial timeout,
    so it is reached at ``high``.  With CoCoA's VBF (``backoff_factor=None``)
    it is not monotonic: 0.99 s × 3ⁿ outgrows 1.0 s × 2ⁿ.  So we also check the
    right end of each VBF band that lies inside the range, taking the limit
    from below for the open bands.  A ``backoff_cap`` (see
    :func:`backed_off_cap`) keeps the total non-decreasing within each band
    (below the cap it is a constant; above it every timeout equals the
    initial one), so the same candidates give the supremum."""
    if high < low:
        raise ValueError("high < low")

    def total(initial: float, factor: float) -> float:
        return _schedule_total(initial, factor, max_retransmit, backed_off_cap(initial, max_timeout, backoff_cap))

    if backoff_factor is not None:
        return total(high, backoff_factor)
    candidates = [total(high, variable_backoff_factor(high))]
    if low < 1.0 <= high:  # sup of the ×3 band [low, 1): its limit at 1 s
        candidates.append(total(1.0, 3.0))
    if low <= 3.0 < high:  # the ×2 band [1, 3] ends, closed, at 3 s
        candidates.append(total(3.0, 2.0))
    return max(candidates)


@dataclass
class RttEstimator:
    """One SRTT/RTTVAR pair (RFC 6298 smoothing) and CoCoA's estimate
    ``E = SRTT + max(G, K·RTTVAR)``.

    ``k`` is 4 for CoCoA's strong estimator (like TCP) and 1 for the weak one.
    Weak samples already contain at least one timeout, so a wide variance
    margin on top would double-count."""

    k: float
    alpha: float = RFC6298_ALPHA
    beta: float = RFC6298_BETA
    granularity: float = CLOCK_GRANULARITY
    srtt: float | None = None
    rttvar: float | None = None
    samples: int = 0

    def update(self, rtt: float) -> float:
        """Fold in one sample and return the new estimate E.

        The first sample sets SRTT=R and RTTVAR=R/2.  Later samples update
        RTTVAR first, using the *old* SRTT as RFC 6298 §2.3 requires, and
        then SRTT."""
        if rtt < 0 or math.isnan(rtt):
            raise ValueError(f"invalid RTT sample {rtt!r}")
        if self.srtt is None or self.rttvar is None:
            self.srtt, self.rttvar = rtt, rtt / 2
        else:
            self.rttvar = (1 - self.beta) * self.rttvar + self.beta * abs(self.srtt - rtt)
            self.srtt = (1 - self.alpha) * self.srtt + self.alpha * rtt
        self.samples += 1
        return self.estimate  # type: ignore[return-value]

    @property
    def estimate(self) -> float | None:
        """E, or None before the first sample."""
        if self.srtt is None or self.rttvar is None:
            return None
        return self.srtt + max(self.granularity, self.k * self.rttvar)


@dataclass
class CocoaRto:
    """Per-peer CoCoA retransmission timeout state.

    Create one per peer (see :meth:`AdaptiveProfile.new_rto`).  Feed it
    :meth:`on_sample` when an exchange completes, and ask
    :meth:`initial_timeout` when a new exchange starts.  Both take ``now``
    because ageing is applied lazily: an idle peer's RTO drifts back towards
    the 1–3 s band the next time anyone looks.

    ``link_rate_bps`` turns on size normalisation (see the module docstring).
    Samples then need ``wire_bytes``, the bytes on the link for the request
    and its reply including IP/UDP headers, and timeouts need the same figure
    for the new exchange's request and expected reply.  With
    ``link_rate_bps=None`` ``wire_bytes`` is ignored and this is plain CoCoA.
    """

    initial_rto: float = 2.0
    rto_cap: float = 32.0
    min_timeout: float = 0.5
    max_timeout: float = 60.0
    dither: float = 1.5
    link_rate_bps: float | None = None
    strong: RttEstimator = field(default_factory=lambda: RttEstimator(k=4.0))
    weak: RttEstimator = field(default_factory=lambda: RttEstimator(k=1.0))
    last_update: float | None = None
    """Time of the last RTO update (sample or ageing step).  None means no
    sample yet, so there is nothing to age and the "blind" rule applies."""
    min_rtt: float | None = None
    """Smallest raw (not size-normalised) strong sample.  It is a lower bound
    on what any reply from this peer can take, and spurious-retransmission
    detection uses it."""

    # ageing thresholds (CoCoA §4.2.2)
    AGE_UP_BELOW: ClassVar[float] = 1.0
    AGE_UP_IDLE_RTOS: ClassVar[float] = 16.0
    AGE_DOWN_ABOVE: ClassVar[float] = 3.0
    AGE_DOWN_IDLE_RTOS: ClassVar[float] = 4.0

    def __post_init__(self) -> None:
        if not 0 < self.min_timeout <= self.max_timeout:
            raise ValueError("need 0 < min_timeout <= max_timeout")
        if self.dither < 1.0:
            raise ValueError("dither must be >= 1")
        if self.link_rate_bps is not None and self.link_rate_bps <= 0:
            raise ValueError("link_rate_bps must be positive")
        self._rto = min(self.initial_rto, self.rto_cap)

    # --------------------------------------------------------------- state

    @property
    def has_samples(self) -> bool:
        """True once a strong or weak sample has been taken."""
        return self.last_update is not None

    def rto(self, now: float) -> float:
        """The overall RTO at ``now``, with any pending ageing applied first."""
        self.age(now)
        return self._rto

    def age(self, now: float) -> None:
        """Apply CoCoA's ageing for the idle time up to ``now``.

        A small RTO (< 1 s) that has not been updated for 16·RTO doubles.  A
        large one (> 3 s) that has not been updated for 4·RTO becomes
        1 s + RTO/2.  Each step uses up its own idle period and moves
        ``last_update`` to the end of it, so a long silence applies several
        steps in a row, each measured with the RTO of the step before.
        Between 1 s and 3 s nothing changes."""
        if self.last_update is None:
            return
        while True:
            idle = now - self.last_update
            if self._rto < self.AGE_UP_BELOW and idle >= self.AGE_UP_IDLE_RTOS * self._rto:
                self.last_update += self.AGE_UP_IDLE_RTOS * self._rto
                self._rto = min(2 * self._rto, self.rto_cap)
            elif self._rto > self.AGE_DOWN_ABOVE and idle >= self.AGE_DOWN_IDLE_RTOS * self._rto:
                self.last_update += self.AGE_DOWN_IDLE_RTOS * self._rto
                self._rto = 1.0 + self._rto / 2
            else:
                return

    def serialisation_time(self, wire_bytes: int) -> float:
        """Time to put ``wire_bytes`` on the link, or 0 if the rate is unknown."""
        if self.link_rate_bps is None or wire_bytes <= 0:
            return 0.0
        return 8.0 * wire_bytes / self.link_rate_bps

    # --------------------------------------------------------------- samples

    def on_sample(
        self,
        rtt: float,
        retransmissions: int,
        now: float,
        wire_bytes: int = 0,
        kind: SampleKind | None = None,
    ) -> SampleKind:
        """Take an RTT sample and update the RTO.  Returns how it was used.

        ``rtt`` runs from the *first* transmission to the reply.
        ``retransmissions`` decides strong, weak or discarded
        (:func:`classify_sample`), unless the caller passes ``kind``.  The
        transport does that when it can prove which transmission the reply
        answered (see :func:`attribute_reply`).

        Strong: ``RTO = 0.5·E_strong + 0.5·RTO``.  Weak:
        ``RTO = 0.25·E_weak + 0.75·RTO``.  The result is capped at
        ``rto_cap``.  Pending ageing is applied before the update."""
        kind = classify_sample(retransmissions) if kind is None else kind
        if kind is SampleKind.DISCARDED:
            return kind
        self.age(now)
        base = max(0.0, rtt - self.serialisation_time(wire_bytes))
        if kind is SampleKind.STRONG:
            estimate = self.strong.update(base)
            self._rto = 0.5 * estimate + 0.5 * self._rto
            self.min_rtt = rtt if self.min_rtt is None else min(self.min_rtt, rtt)
        else:
            estimate = self.weak.update(base)
            self._rto = 0.25 * estimate + 0.75 * self._rto
        self._rto = min(self._rto, self.rto_cap)
        self.last_update = now
        return kind

    # --------------------------------------------------------------- timeouts

    def initial_timeout(
        self,
        rng: random.Random,
        now: float,
        wire_bytes: int = 0,
        outstanding: int = 1,
    ) -> float:
        """Initial timeout for a new exchange:
        ``uniform[RTO, dither·RTO] + serialisation(wire_bytes)``, clamped to
        ``[min_timeout, max_timeout]``.

        The dithering keeps peers that start together from retransmitting in
        step.  Before the first sample the "blind" rule applies: the RTO is
        multiplied by ``outstanding``, the number of exchanges in flight to
        this peer including this one (capped at ``rto_cap``).  With aiocoap's
        NSTART=1 that number is 1."""
        rto = self.rto(now)
        if not self.has_samples and outstanding > 1:
            rto = min(rto * outstanding, self.rto_cap)
        drawn = rng.uniform(rto, self.dither * rto) + self.serialisation_time(wire_bytes)
        return self.clamp(drawn)

    def clamp(self, timeout: float) -> float:
        """Clamp a timeout to ``[min_timeout, max_timeout]``."""
        return min(max(timeout, self.min_timeout), self.max_timeout)

    @staticmethod
    def backoff_factor(initial_timeout: float) -> float:
        """CoCoA's variable backoff factor; see :func:`variable_backoff_factor`."""
        return variable_backoff_factor(initial_timeout)

    def initial_timeout_range(self, now: float, wire_bytes: int = 0) -> tuple[float, float]:
        """The interval :meth:`initial_timeout` draws from at ``now``, with one
        exchange outstanding."""
        rto = self.rto(now)
        ser = self.serialisation_time(wire_bytes)
        return self.clamp(rto + ser), self.clamp(self.dither * rto + ser)

    def as_dict(self, now: float) -> dict[str, Any]:
        """Snapshot for logs and the agent's record."""
        return {
            "rto": self.rto(now),
            "srtt_strong": self.strong.srtt,
            "rttvar_strong": self.strong.rttvar,
            "samples_strong": self.strong.samples,
            "srtt_weak": self.weak.srtt,
            "rttvar_weak": self.weak.rttvar,
            "samples_weak": self.weak.samples,
            "min_rtt": self.min_rtt,
            "link_rate_bps": self.link_rate_bps,
        }


def attribute_reply(
    transmit_times: Sequence[float],
    reply_time: float,
    min_rtt: float | None,
    fraction: float = 0.5,
) -> int:
    """Index of the latest transmission that can have produced a reply that
    arrived at ``reply_time``.

    A copy sent at ``t`` cannot be answered before ``t + min_rtt``.  To allow
    for a path that has got faster since ``min_rtt`` was seen, we only trust
    ``fraction·min_rtt``.  Every transmission after the returned index was
    therefore sent *after* a copy that did get through, so it is a provably
    spurious retransmission: ``len(transmit_times) - 1 - index`` of them.
    With no ``min_rtt`` there is no evidence and the last index is returned.
    A return of 0 with retransmissions means the reply answered the original
    transmission, so ``reply_time - transmit_times[0]`` is an unambiguous
    (strong) sample.  The same idea as Eifel/F-RTO for TCP, except that
    without timestamps CoAP can only use the minimum RTT as its evidence."""
    if not transmit_times:
        raise ValueError("no transmissions")
    last = len(transmit_times) - 1
    if min_rtt is None or min_rtt <= 0:
        return last
    threshold = fraction * min_rtt
    for index in range(last, -1, -1):
        if reply_time - transmit_times[index] >= threshold:
            return index
    return 0  # faster than anything seen: must still be the original


# ------------------------------------------------------------------ profiles


@dataclass(frozen=True)
class RetransmissionSchedule:
    """The timeouts of one CON exchange, fixed when it is first transmitted.

    Timeout ``n`` (the wait after transmission ``n``, 0 = original) is
    ``min(initial_timeout · backoff_factor**n, max_timeout)``.  After
    ``max_retransmit`` retransmissions, the last timeout ends the exchange
    with a failure."""

    initial_timeout: float
    backoff_factor: float
    max_retransmit: int
    max_timeout: float = math.inf

    def timeout(self, n: int) -> float:
        """Wait after transmission ``n`` (0 = original)."""
        return min(self.initial_timeout * self.backoff_factor**n, self.max_timeout)

    def timeouts(self) -> tuple[float, ...]:
        return tuple(self.timeout(n) for n in range(self.max_retransmit + 1))

    @property
    def transmit_offsets(self) -> tuple[float, ...]:
        """When each transmission goes out, relative to the first."""
        offsets, t = [], 0.0
        for n in range(self.max_retransmit + 1):
            offsets.append(t)
            t += self.timeout(n)
        return tuple(offsets)

    @property
    def total_wait(self) -> float:
        """First transmission → giving up (the MAX_TRANSMIT_WAIT of this exchange)."""
        return sum(self.timeouts())


@dataclass(frozen=True, kw_only=True)
class TransmissionProfile(abc.ABC):
    """How CON requests are retransmitted: a named, immutable configuration.

    ``schedule`` draws the timeouts of one exchange.  ``new_rto`` creates the
    per-peer estimator.  Every profile measures RTTs, even the fixed ones, so
    runs with different profiles record comparable statistics.
    ``max_transmit_wait`` bounds how long one exchange can last, so callers
    can bound their own timeouts."""

    name: str
    max_retransmit: int

    kind: ClassVar[str]

    @abc.abstractmethod
    def new_rto(self) -> CocoaRto:
        """Fresh per-peer RTO state."""

    @abc.abstractmethod
    def schedule(
        self,
        rng: random.Random,
        rto: CocoaRto,
        now: float,
        wire_bytes: int = 0,
        outstanding: int = 1,
    ) -> RetransmissionSchedule:
        """Timeouts for an exchange starting at ``now`` to the peer owning ``rto``."""

    @abc.abstractmethod
    def max_transmit_wait(self) -> float:
        """Upper bound (s) from the first transmission of one exchange to
        giving up, whatever the peer's state."""

    @abc.abstractmethod
    def max_transmit_span(self) -> float:
        """Upper bound (s) from the first transmission to the last retransmission."""

    def as_dict(self) -> dict[str, Any]:
        """Parameters and bounds, for the agent's run record."""
        d = {k: (None if isinstance(v, float) and math.isinf(v) else v) for k, v in asdict(self).items()}
        d["kind"] = self.kind
        d["max_transmit_span"] = self.max_transmit_span()
        d["max_transmit_wait"] = self.max_transmit_wait()
        return d


@dataclass(frozen=True, kw_only=True)
class FixedProfile(TransmissionProfile):
    """RFC 7252 timers with configurable constants: the initial timeout is
    ``uniform[ack_timeout, ack_timeout·ack_random_factor]``, then multiplied by
    ``backoff_factor`` for each retransmission and capped at ``max_timeout``.
    ``backoff_factor=2`` with no cap is RFC 7252 and aiocoap's behaviour."""

    ack_timeout: float
    ack_random_factor: float
    backoff_factor: float = 2.0
    max_timeout: float = math.inf

    kind: ClassVar[str] = "fixed"

    def __post_init__(self) -> None:
        if self.ack_timeout <= 0 or self.ack_random_factor < 1 or self.backoff_factor < 1:
            raise ValueError("invalid fixed profile")

    def new_rto(self) -> CocoaRto:
        # Measurement only: lets the record show what the adaptive RTO would be.
        return CocoaRto()

    def schedule(
        self,
        rng: random.Random,
        rto: CocoaRto,
        now: float,
        wire_bytes: int = 0,
        outstanding: int = 1,
    ) -> RetransmissionSchedule:
        return self._from_initial(rng.uniform(self.ack_timeout, self.ack_timeout * self.ack_random_factor))

    def _worst(self) -> RetransmissionSchedule:
        return self._from_initial(self.ack_timeout * self.ack_random_factor)

    def _from_initial(self, initial: float) -> RetransmissionSchedule:
        return RetransmissionSchedule(
            initial_timeout=min(initial, self.max_timeout),
            backoff_factor=self.backoff_factor,
            max_retransmit=self.max_retransmit,
            max_timeout=self.max_timeout,
        )

    def max_transmit_wait(self) -> float:
        return self._worst().total_wait

    def max_transmit_span(self) -> float:
        return self._worst().total_wait - self._worst().timeout(self.max_retransmit)


@dataclass(frozen=True, kw_only=True)
class AdaptiveProfile(TransmissionProfile):
    """CoCoA: a per-peer RTO from measured RTTs, dithered initial timeout,
    variable backoff factor (:func:`variable_backoff_factor`), and each
    timeout capped at ``max_timeout``.  ``link_rate_bps`` turns on size
    normalisation (see the module docstring).  :meth:`with_link_rate` fills
    it in from the link configuration.

    ``backoff_cap`` (coapkb's choice, 8 s as in ``lossy-fixed``) stops the
    backoff once a timeout reaches it, unless the initial timeout is already
    longer (then every timeout equals the initial one; see
    :func:`backed_off_cap`).  Why: CoCoA's VBF of 3 for sub-second timeouts
    gives, from the 0.5 s clamp, waits of 0.5, 1.5, 4.5, 13.5, 40.5, 60, 60 s
    with our 6 retransmissions.  Under random loss the 13.5 s and later waits
    only add latency: measured on emulated 20 % loss links they made the
    adaptive tail longer than ``lossy-fixed``'s, and a give-up took 180 s,
    longer than the agents' query timeouts (see docs/retransmission.md,
    "Measured on emulated links").  With the cap the early backoff is still
    CoCoA's (×3 or ×2), a stuck exchange sends at most one datagram per 8 s,
    and a give-up from the clamp takes 38.5 s.  ``None`` restores plain
    CoCoA."""

    name: str = "adaptive"
    max_retransmit: int = 6
    initial_rto: float = 2.0
    rto_cap: float = 32.0
    min_timeout: float = 0.5
    max_timeout: float = 60.0
    dither: float = 1.5
    link_rate_bps: float | None = None
    backoff_cap: float | None = 8.0

    kind: ClassVar[str] = "adaptive"

    def __post_init__(self) -> None:
        if self.backoff_cap is not None and self.backoff_cap <= 0:
            raise ValueError("backoff_cap must be positive (or None for plain CoCoA)")

    def with_link_rate(self, link_rate_bps: float | None) -> "AdaptiveProfile":
        return replace(self, link_rate_bps=link_rate_bps)

    def new_rto(self) -> CocoaRto:
        return CocoaRto(
            initial_rto=self.initial_rto,
            rto_cap=self.rto_cap,
            min_timeout=self.min_timeout,
            max_timeout=self.max_timeout,
            dither=self.dither,
            link_rate_bps=self.link_rate_bps,
        )

    def schedule(
        self,
        rng: random.Random,
        rto: CocoaRto,
        now: float,
        wire_bytes: int = 0,
        outstanding: int = 1,
    ) -> RetransmissionSchedule:
        initial = rto.initial_timeout(rng, now, wire_bytes=wire_bytes, outstanding=outstanding)
        return RetransmissionSchedule(
            initial_timeout=initial,
            backoff_factor=variable_backoff_factor(initial),
            max_retransmit=self.max_retransmit,
            max_timeout=backed_off_cap(initial, self.max_timeout, self.backoff_cap),
        )

    def _initial_bounds(self) -> tuple[float, float]:
        # Largest possible initial timeout: RTO at its cap, fully dithered,
        # plus one full-size exchange's serialisation.
        ser = 0.0 if self.link_rate_bps is None else 8.0 * 2 * (DEFAULT_REPLY_BYTES + 48) / self.link_rate_bps
        high = min(max(self.rto_cap * self.dither + ser, self.min_timeout), self.max_timeout)
        return self.min_timeout, high

    def max_transmit_wait(self) -> float:
        low, high = self._initial_bounds()
        return worst_case_wait(low, high, self.max_retransmit, self.max_timeout, backoff_cap=self.backoff_cap)

    def max_transmit_span(self) -> float:
        # The last timeout is at most max_timeout and at least min_timeout; the
        # bound below is conservative (it keeps a min_timeout of the last wait).
        return self.max_transmit_wait() - self.min_timeout

    def max_transmit_wait_for(self, rto: CocoaRto, now: float, wire_bytes: int = 0) -> float:
        """Tighter bound for the next exchange to a peer in state ``rto``:
        the worst case over the initial timeouts it can currently draw."""
        low, high = rto.initial_timeout_range(now, wire_bytes)
        return worst_case_wait(low, high, self.max_retransmit, self.max_timeout, backoff_cap=self.backoff_cap)


PROFILES: dict[str, TransmissionProfile] = {
    # RFC 7252 §4.8 defaults (what aiocoap does on its own): 2-3 s, doubling,
    # 4 retransmissions -> MAX_TRANSMIT_WAIT 93 s.
    "rfc7252": FixedProfile(name="rfc7252", ack_timeout=2.0, ack_random_factor=1.5, max_retransmit=4),
    # Fixed short timers for 35-512 kbit/s links with up to 20 % loss; the
    # reasoning is in docs/retransmission.md ("lossy-fixed").  Worst-case
    # exchange RTT at 35 kbit/s (1.1 KB each way + 100 ms server delay +
    # propagation) is ~0.7 s, so 0.8-1.0 s never fires spuriously; 7
    # transmissions at 36 % per-attempt failure leave 8e-4 per exchange; the
    # 8 s cap bounds a give-up at 39 s instead of 127 s.
    "lossy-fixed": FixedProfile(
        name="lossy-fixed",
        ack_timeout=0.8,
        ack_random_factor=1.25,
        max_retransmit=6,
        backoff_factor=2.0,
        max_timeout=8.0,
    ),
    # CoCoA (draft-ietf-core-cocoa-03) with the same retransmission budget as
    # lossy-fixed, so that comparisons isolate the timeout policy, and its
    # backoff capped at 8 s like lossy-fixed's (see AdaptiveProfile).
    "adaptive": AdaptiveProfile(),
}


def get_profile(name_or_profile: str | TransmissionProfile) -> TransmissionProfile:
    """Look a profile up by name (``rfc7252``, ``lossy-fixed``, ``adaptive``)
    or pass one through."""
    if isinstance(name_or_profile, TransmissionProfile):
        return name_or_profile
    try:
        return PROFILES[name_or_profile]
    except KeyError:
        raise ValueError(f"unknown transmission profile {name_or_profile!r}; known: {sorted(PROFILES)}") from None
