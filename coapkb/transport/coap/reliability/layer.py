"""The reliability layer for robot-to-robot exchanges on slow, lossy links.

RFC 7252's confirmable retransmission treats every loss as congestion (a
2-3 s first timeout, doubled per retry, one exchange at a time per peer);
on a radio link that loses datagrams at random, one loss becomes seconds of
silence.  This layer keeps CoAP's messages and options and changes how they
are retried: each try is a new NON exchange with a fresh token (so every
answer is an unambiguous RTT sample, and the request must be idempotent);
the timeout follows RFC 6298 over those samples plus the exchange's extra
airtime, and grows only on evidence of a queue or of a long silence, never
on a loss; a window of exchanges in flight per peer; and retries sent as
two copies when the measured loss is high.  :class:`ReliabilitySettings`
holds every knob (a robot's ``[transport.coap]`` table),
:class:`PeerPath` one path's estimates, :class:`ReliabilityLayer` the
exchange loop; the server's CON notifications follow the same estimates
(:mod:`.notifications`).

docs/reliability.md gives each choice with its reason and the measured
figures; docs/configuration.md the settings and their defaults.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import OrderedDict, deque
from collections.abc import Awaitable, Callable, Hashable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Generic, TypeVar

from ...rtt import RttEstimator
from .estimator import LossEstimator, UplinkQueue, airtime

log = logging.getLogger(__name__)

__all__ = ["ReliabilitySettings", "PathStats", "PeerPath", "ReliabilityLayer", "Attempt", "ExchangeTimeout"]

T = TypeVar("T")

#: Reply size assumed for a resource never answered before: a small answer.
DEFAULT_REPLY_BYTES = 128
#: Outcomes on a path before its loss estimate decides the copies of a try.
TRUSTED_OUTCOMES = 8
#: Tries of one request that may fail outright (ICMP) before the error is raised.
MAX_ERRORS = 2


def _answered(attempt: Attempt[Any]) -> bool:
    task = attempt.task
    return task is not None and task.done() and not task.cancelled() and task.exception() is None


def _failed(attempt: Attempt[Any]) -> bool:
    task = attempt.task
    return task is not None and task.done() and not task.cancelled() and task.exception() is not None


def _answer(attempt: Attempt[T]) -> T:
    """What an answered try (:func:`_answered`) returned."""
    assert attempt.task is not None
    return attempt.task.result()


def _error(attempt: Attempt[Any]) -> BaseException:
    """What a failed try (:func:`_failed`) raised."""
    error = attempt.task.exception() if attempt.task is not None else None
    assert error is not None
    return error


#: An exchange answered later than this is logged (INFO) with its tries:
#: the tail of a lossy link, told try by try.
SLOW_EXCHANGE_S = 1.0


def _log_slow(peer: Hashable, reply_key: Hashable, started: float, now: float, attempts: Sequence[Attempt[Any]],
              winner: Attempt[Any], path: PeerPath) -> None:
    tries = ", ".join(f"{a.try_number}@{a.sent_at - started:.2f}s/{a.timeout:.2f}s" for a in attempts)
    log.info("slow exchange with %s (%s): answered after %.2f s by try %d; tries (number@sent/timeout): %s; "
             "srtt %s, loss %.2f, congested %s", peer, reply_key, now - started, winner.try_number, tries,
             None if path.rtt.srtt is None else round(path.rtt.srtt, 3), path.loss.rate, path.congested())


@dataclass(frozen=True)
class ReliabilitySettings:
    """Policy knobs of the layer (validated; times in seconds)."""

    #: Rate of the robot's radio link, if known (kbit/s): airtime in the timeout, window size.
    link_kbps: float | None = None
    min_rto: float = 0.05
    #: The floor when the link rate is not known: samples then mix sizes, and
    #: a shaper's burst allowance makes the first ones far too short.
    min_rto_unknown_link: float = 0.2
    max_rto: float = 8.0
    #: Timeout of a path with no sample yet (RFC 6298: 1 s).
    initial_rto: float = 1.0
    #: The same on a link of known rate: the exchange's airtime at that rate
    #: and the robot's own queue are added to it, so half a second covers a
    #: peer's queue of a few exchanges at 35 kbit/s.  RFC 6298's second is
    #: for a path nothing is known of; here it made every loss among the
    #: first exchanges with a teammate (EDHOC's, the first query) cost one.
    initial_rto_known_link: float = 0.5
    rto_k: float = 4.0
    granularity: float = 0.01
    #: Round-trip loss above which retries go out as two copies, and above which every try does.
    hedge_retries_above: float = 0.10
    hedge_all_above: float = 0.50
    #: Least spacing between the copies of one try (plus one request's airtime).
    hedge_gap: float = 0.01
    max_copies: int = 2
    #: A try whose answer is expected larger than this goes out as one copy:
    #: both copies reach the server more often than not, and each is
    #: answered, so a block of a long answer crossed the link twice (0.25 s
    #: of airtime at 35 kbit/s; catch-up at 20 % loss received 8 blocks for 4).
    hedge_reply_bytes_max: int = 512
    #: Queueing evidence: SRTT above min RTT by this factor and by ``congestion_slack``
    #: (a few answers queued ahead at 35 kbit/s are normal; a standing queue is not).
    congestion_factor: float = 2.0
    congestion_slack: float = 0.3
    #: Silence evidence: the oldest unanswered send this many timeouts old (and at least 1 s).
    silence_timeouts: float = 4.0
    #: The most a try waits on a silent (not congested) path...
    silence_rto: float = 1.0
    #: ...while the silence is shorter than this; past it the tries back off
    #: by doubling to ``max_rto``: a silence that long is a queue (a server
    #: shared by a whole team) far more often than random loss, and one try
    #: a second from each of 99 robots kept a central server's link full.
    long_silence_s: float = 5.0
    window_min: int = 2
    window_max: int = 16
    max_tries: int = 30
    #: Of an observation's notifications, every this many is confirmable
    #: (the rest NON, repaired by the waiting observer; 1: all confirmable).
    confirm_every: int = 16

    def __post_init__(self) -> None:
        if self.link_kbps is not None and not self.link_kbps > 0:
            raise ValueError("link_kbps must be positive")
        if not 0 < self.min_rto <= min(self.initial_rto, self.initial_rto_known_link) or max(
                self.initial_rto, self.initial_rto_known_link) > self.max_rto:
            raise ValueError("need 0 < min_rto <= initial_rto, initial_rto_known_link <= max_rto")
        if not self.min_rto <= self.silence_rto <= self.max_rto:
            raise ValueError("need min_rto <= silence_rto <= max_rto")
        if not self.long_silence_s > 0:
            raise ValueError("long_silence_s must be positive")
        if not 0 <= self.hedge_retries_above <= self.hedge_all_above <= 1:
            raise ValueError("need 0 <= hedge_retries_above <= hedge_all_above <= 1")
        if not 1 <= self.window_min <= self.window_max:
            raise ValueError("need 1 <= window_min <= window_max")
        if self.max_copies < 1 or self.max_tries < 1 or self.confirm_every < 1:
            raise ValueError("max_copies, max_tries and confirm_every must be at least 1")
        if self.hedge_reply_bytes_max < 0:
            raise ValueError("hedge_reply_bytes_max must not be negative")

    @property
    def link_bps(self) -> float | None:
        return None if self.link_kbps is None else self.link_kbps * 1000.0


class ExchangeTimeout(TimeoutError):
    """No try of an exchange was answered before its deadline."""


@dataclass
class PathStats:
    """What happened on one path (the agent's record carries these)."""

    requests: int = 0
    completed: int = 0
    failed: int = 0
    tries: int = 0
    #: Datagrams sent for requests: first copies, retries and hedge copies.
    attempts: int = 0
    retries: int = 0
    hedge_copies: int = 0
    #: Retries sent after the try that was answered had left: not needed.
    spurious_retransmissions: int = 0
    answered_by_earlier_try: int = 0
    samples: int = 0
    backoffs: int = 0
    window_waits: int = 0
    notifications: int = 0
    notification_retransmissions: int = 0
    #: Notifications whose duplicate ACK showed a retransmission was needless.
    needless_notification_retransmissions: int = 0
    srtt: float | None = None
    rttvar: float | None = None
    min_rtt: float | None = None
    rto: float | None = None
    loss: float | None = None
    window: int | None = None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class PeerPath:
    """What the layer knows of one peer: its estimators, window and counters,
    and the policy decisions that follow from them."""

    def __init__(self, settings: ReliabilitySettings) -> None:
        self.settings = settings
        self.rtt = RttEstimator()
        self.loss = LossEstimator()
        self.stats = PathStats()
        self.inflight = 0
        self.waiters: deque[asyncio.Future[None]] = deque()
        #: When the oldest send that no answer has followed went out (None:
        #: every send answered).  Silence is counted from it, not from the
        #: last answer: a peer asked seldom (its facts are pushed) is not
        #: silent because nothing was asked of it for a while.
        self.unanswered_since: float | None = None
        #: EWMA of answer sizes per resource, to time an answer before it comes.
        self.reply_bytes: OrderedDict[Hashable, float] = OrderedDict()
        #: EWMA of the bytes of the exchanges the samples come from.
        self.sampled_bytes: float | None = None

    # ---- policy

    def floor(self) -> float:
        s = self.settings
        return s.min_rto if s.link_bps else max(s.min_rto, s.min_rto_unknown_link)

    def initial_rto(self) -> float:
        """The timeout of a path with no sample yet."""
        s = self.settings
        return s.initial_rto_known_link if s.link_bps else s.initial_rto

    def rto(self) -> float:
        s = self.settings
        return self.rtt.rto(k=s.rto_k, granularity=s.granularity, floor=self.floor(), ceiling=s.max_rto,
                            initial=self.initial_rto())

    def exchange_timeout(self, base: float, exchange_bytes: float) -> float:
        """``base`` (the RTO, maybe backed off) plus the airtime by which this
        exchange exceeds the sampled ones; never less than the floor plus its
        whole airtime at the line rate, since samples taken while a shaper's
        burst allowance lasted are shorter than the line allows."""
        s = self.settings
        return max(min(s.max_rto, base) + self.extra_airtime(exchange_bytes),
                   self.floor() + airtime(exchange_bytes, s.link_bps))

    def congested(self) -> bool:
        s = self.settings
        if self.rtt.samples < 4 or self.rtt.min_rtt is None or self.rtt.srtt is None:
            return False
        return self.rtt.srtt > s.congestion_factor * self.rtt.min_rtt + s.congestion_slack

    def silent(self, now: float) -> bool:
        """No answer for several timeouts while we kept sending: down or cut off."""
        if self.unanswered_since is None:
            return False
        return now - self.unanswered_since > max(1.0, self.settings.silence_timeouts * self.rto())

    def on_send(self, now: float) -> None:
        if self.unanswered_since is None:
            self.unanswered_since = now

    def on_answer(self) -> None:
        self.unanswered_since = None

    def window(self) -> int:
        s = self.settings
        if self.congested():
            return s.window_min
        if s.link_bps is None or self.rtt.srtt is None:
            return s.window_max
        exchange_bytes = 64 + self.expected_reply(None)
        bdp_bytes = s.link_bps / 8 * self.rtt.srtt
        return max(s.window_min, min(s.window_max, math.ceil(bdp_bytes / exchange_bytes) + 1))

    def copies(self, try_number: int, now: float, reply_bytes: float = 0.0) -> int:
        s = self.settings
        if reply_bytes > s.hedge_reply_bytes_max:
            return 1
        if self.silent(now):
            # Nothing answered for several timeouts: more copies would only
            # add to a queue, if that is what holds the answers.
            return 1
        if self.loss.observed < TRUSTED_OUTCOMES:
            # Too few outcomes to trust the estimate: a try that went
            # unanswered is the evidence there is.  Its retry goes out twice,
            # so a new path's first exchanges (EDHOC, a task's first query)
            # do not wait out loss after loss with one copy at a time.
            return min(2, s.max_copies) if try_number > 0 else 1
        if self.loss.rate > s.hedge_all_above or (try_number > 0 and self.loss.rate > s.hedge_retries_above):
            return min(2, s.max_copies)
        return 1

    def try_timeout(self, try_number: int, request_bytes: int, reply_key: Hashable, now: float) -> float:
        base = self.rto()
        if try_number and self.congested():
            base *= 2 ** min(try_number, 8)
            self.stats.backoffs += 1
        elif try_number and self.silent(now):
            assert self.unanswered_since is not None
            quiet = now - self.unanswered_since
            cap = self.settings.silence_rto if quiet < self.settings.long_silence_s else self.settings.max_rto
            if base < cap:
                base = min(base * 2 ** min(try_number, 8), cap)
                self.stats.backoffs += 1
        return self.exchange_timeout(base, request_bytes + self.expected_reply(reply_key))

    def extra_airtime(self, exchange_bytes: float) -> float:
        """How much longer than the sampled exchanges one of ``exchange_bytes`` takes on the link."""
        if self.sampled_bytes is None:
            return airtime(exchange_bytes, self.settings.link_bps)
        link = self.settings.link_bps
        return max(0.0, airtime(exchange_bytes, link) - airtime(self.sampled_bytes, link))

    def on_sample(self, rtt: float, exchange_bytes: float) -> None:
        self.rtt.on_sample(rtt)
        self.sampled_bytes = exchange_bytes if self.sampled_bytes is None else (
            0.875 * self.sampled_bytes + 0.125 * exchange_bytes)

    def expected_reply(self, reply_key: Hashable | None) -> float:
        if reply_key is None:
            if not self.reply_bytes:
                return DEFAULT_REPLY_BYTES
            return sum(self.reply_bytes.values()) / len(self.reply_bytes)
        return self.reply_bytes.get(reply_key, DEFAULT_REPLY_BYTES)

    def note_reply_size(self, reply_key: Hashable, nbytes: int) -> None:
        old = self.reply_bytes.pop(reply_key, None)
        self.reply_bytes[reply_key] = float(nbytes) if old is None else 0.75 * old + 0.25 * nbytes
        while len(self.reply_bytes) > 256:
            self.reply_bytes.popitem(last=False)

    # ---- window

    async def admit(self) -> None:
        if self.inflight >= self.window():
            self.stats.window_waits += 1
            while self.inflight >= self.window():
                waiter = asyncio.get_running_loop().create_future()
                self.waiters.append(waiter)
                try:
                    await waiter
                except asyncio.CancelledError:
                    if waiter in self.waiters:
                        self.waiters.remove(waiter)
                    elif self.waiters:  # we were woken and are leaving: pass the turn on
                        self._wake_one()
                    raise
        self.inflight += 1

    def release(self) -> None:
        self.inflight -= 1
        self._wake_one()

    def _wake_one(self) -> None:
        while self.waiters:
            waiter = self.waiters.popleft()
            if not waiter.done():
                waiter.set_result(None)
                return

    def snapshot(self) -> PathStats:
        stats = PathStats(**asdict(self.stats))
        stats.srtt, stats.min_rtt = self.rtt.srtt, self.rtt.min_rtt
        stats.rttvar = self.rtt.rttvar if self.rtt.samples else None
        stats.rto, stats.loss, stats.window = self.rto(), self.loss.rate, self.window()
        return stats


@dataclass
class Attempt(Generic[T]):
    """One try's copy in flight: its answer-to-be and how to abandon it."""

    answer: Awaitable[T]
    cancel: Callable[[], None]
    try_number: int = 0
    sent_at: float = 0.0
    #: Link time of what was queued ahead of this try when it was sent.
    queued: float = 0.0
    timeout: float = 0.0
    #: The transport's own handle of this try (an aiocoap request, say).
    handle: Any = field(default=None, repr=False)
    task: asyncio.Future[T] | None = field(default=None, repr=False)


class ReliabilityLayer:
    """Exchanges with peers, retried as fresh exchanges (see the module doc).

    Transport-agnostic: :meth:`exchange` is given a function that sends one
    try and returns an :class:`Attempt`; the CoAP client builds a new aiocoap
    NON request each time.  One layer serves a robot's client and its
    server's notifications, so both use the same path estimates."""

    #: Its name in records (``profile.name`` of :meth:`as_dict`).
    name = "robust"

    def __init__(self, settings: ReliabilitySettings | None = None, *, clock: Callable[[], float] = time.monotonic) -> None:
        self.settings = settings or ReliabilitySettings()
        self.clock = clock
        self._paths: dict[Hashable, PeerPath] = {}
        #: The robot's own link: both its client's and its server's datagrams.
        self.uplink = UplinkQueue(self.settings.link_bps)

    @property
    def confirm_every(self) -> int:
        return self.settings.confirm_every

    def on_datagram(self, nbytes: int) -> None:
        """Hand this every datagram the robot sends (the CoAP contexts do)."""
        self.uplink.on_sent(nbytes, self.clock())

    def path(self, peer: Hashable) -> PeerPath:
        path = self._paths.get(peer)
        if path is None:
            path = self._paths[peer] = PeerPath(self.settings)
        return path

    def path_for_host(self, host: str) -> PeerPath:
        """The path with the most samples to any port of ``host`` (the
        server's notifications go to the peer's client port, not its
        server's); a path of its own for a host never asked anything (the
        feeder, a person's client), which the notifications' ACKs then train."""
        candidates = [p for key, p in self._paths.items() if getattr(key, "host", None) == host]
        if candidates:
            return max(candidates, key=lambda p: p.rtt.samples)
        return self.path(host)

    async def exchange(
        self,
        peer: Hashable,
        send: Callable[[int], Attempt[T]],
        *,
        timeout: float,
        request_bytes: int,
        reply_key: Hashable = None,
        reply_size: Callable[[T], int] = lambda _: DEFAULT_REPLY_BYTES,
    ) -> tuple[T, Attempt[T]]:
        """Send tries until one is answered; returns the answer and the try
        that got it (its abandonment function is *not* called: an Observe
        registration lives on).  ``send(try_number)`` sends one copy.

        Raises :class:`ExchangeTimeout` when ``timeout`` passes or the tries
        run out.  A try that fails outright (an ICMP error) is tried again at
        once, and the error is raised only when it repeats: Linux reports a
        pending ICMP error on the next send of the socket, whatever its
        destination, so one error may belong to another peer."""
        path = self.path(peer)
        path.stats.requests += 1
        started = self.clock()
        deadline = started + timeout
        async with asyncio.timeout(timeout):
            await path.admit()
        attempts: list[Attempt[T]] = []
        winner: Attempt[T] | None = None
        errors: list[BaseException] = []
        counted: set[int] = set()  # attempts whose error is in ``errors``
        try:
            for try_number in range(self.settings.max_tries):
                now = self.clock()
                if now >= deadline:
                    break
                try_timeout = path.try_timeout(try_number, request_bytes, reply_key, now)
                await self._send_try(path, send, try_number, try_timeout, attempts, path.expected_reply(reply_key))
                while True:
                    answered = [a for a in attempts if _answered(a)]
                    if answered:
                        winner = answered[0]
                        answer = _answer(winner)
                        self._on_answer(path, winner, attempts, reply_key, reply_size(answer), request_bytes)
                        if self.clock() - started > SLOW_EXCHANGE_S:
                            _log_slow(peer, reply_key, started, self.clock(), attempts, winner, path)
                        return answer, winner
                    failed = [a for a in attempts if _failed(a) and id(a) not in counted]
                    if failed:
                        counted.update(id(a) for a in failed)
                        errors.extend(_error(a) for a in failed)
                        if len(errors) >= MAX_ERRORS:
                            raise errors[-1]
                        break  # the next try, at once
                    pending = {a.task for a in attempts if a.task is not None and not a.task.done()}
                    wait = min(attempts[-1].timeout, deadline - self.clock())
                    if wait <= 0 or not pending:
                        break
                    done, _ = await asyncio.wait(pending, timeout=wait, return_when=asyncio.FIRST_COMPLETED)
                    if not done:
                        break  # timed out: the next try
                path.stats.tries += 1
            path.stats.failed += 1
            self._on_give_up(path, attempts)
            raise ExchangeTimeout(f"no answer after {len(attempts)} attempts in {timeout:g}s")
        finally:
            for attempt in attempts:
                if attempt is not winner:
                    attempt.cancel()
                    if attempt.task is not None and not attempt.task.done():
                        attempt.task.cancel()
            path.release()

    async def _send_try(self, path: PeerPath, send: Callable[[int], Attempt[T]], try_number: int,
                        try_timeout: float, attempts: list[Attempt[T]], reply_bytes: float) -> None:
        copies = path.copies(try_number, self.clock(), reply_bytes)
        for copy in range(copies):
            if copy:
                # Spaced apart, so one burst of loss is less likely to take both.
                gap = self.settings.hedge_gap + airtime(64, self.settings.link_bps)
                await asyncio.sleep(gap)
                # Checked after the gap: an answer that came during it makes the copy useless.
                if any(a.task is not None and a.task.done() for a in attempts):
                    return
                path.stats.hedge_copies += 1
            attempt = send(try_number)
            now = self.clock()
            # The timer runs from when the datagram leaves the robot's link.
            attempt.try_number, attempt.sent_at, attempt.queued = try_number, now, self.uplink.wait(now)
            attempt.timeout = try_timeout + attempt.queued
            attempt.task = asyncio.ensure_future(attempt.answer)
            attempts.append(attempt)
            path.stats.attempts += 1
            path.on_send(attempt.sent_at)
            if try_number and not copy:
                path.stats.retries += 1


    def _on_answer(self, path: PeerPath, winner: Attempt[T], attempts: list[Attempt[T]], reply_key: Hashable,
                   reply_bytes: int, winner_request_bytes: int) -> None:
        now = self.clock()
        stats = path.stats
        stats.completed += 1
        path.on_answer()
        # The try's own token names it: this RTT is unambiguous.
        path.on_sample(now - winner.sent_at - winner.queued, winner_request_bytes + reply_bytes)
        stats.samples += 1
        path.note_reply_size(reply_key, reply_bytes)
        if winner.try_number < max(a.try_number for a in attempts):
            stats.answered_by_earlier_try += 1
            stats.spurious_retransmissions += sum(
                1 for a in attempts if a.try_number > winner.try_number and a.sent_at >= winner.sent_at
            )
        for attempt in attempts:
            if attempt is winner:
                path.loss.on_outcome(False)
            elif attempt.sent_at < winner.sent_at and now - attempt.sent_at >= attempt.timeout:
                # Sent before the answered try, had its full time, unanswered:
                # lost.  (Tries sent after it say nothing: they were cut short.)
                path.loss.on_outcome(True)

    def _on_give_up(self, path: PeerPath, attempts: list[Attempt[T]]) -> None:
        now = self.clock()
        for attempt in attempts:
            if now - attempt.sent_at >= attempt.timeout:
                path.loss.on_outcome(True)

    # ------------------------------------------------------------ reporting

    def stats(self) -> dict[str, PathStats]:
        return {str(key): path.snapshot() for key, path in self._paths.items()}

    def as_dict(self) -> dict[str, Any]:
        return {
            "profile": {"name": self.name, **asdict(self.settings)},
            "peers": {key: stats.as_dict() for key, stats in self.stats().items()},
        }
