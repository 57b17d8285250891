"""Link specifications and counters of the emulated links (no side effects here)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ...errors import CoapkbError

__all__ = [
    "BURST_SECONDS",
    "DEFAULT_QUEUE_BYTES",
    "ETH_FRAME_MAX",
    "LOSS_MODELS",
    "LOSS_SCALE",
    "MIN_BURST_BYTES",
    "LinkCounters",
    "LinkEmulationError",
    "LinkSpec",
]

#: Largest frame on the emulated link: 1500-byte MTU plus the 14-byte Ethernet
#: header (``tc`` sees frames without preamble or FCS).
ETH_FRAME_MAX = 1514

#: Token-bucket depth floor.  It must hold one full frame (tbf cannot send a
#: packet larger than its bucket) with margin for tc's rounding to timer
#: ticks, and stay below two full frames so back-to-back frames are already
#: paced: after an idle period a link sends at most ~2 KiB at "line rate",
#: which is 0.47 s worth of credit at 35 kbit/s but invisible in the
#: long-run rate.
MIN_BURST_BYTES = 2048

#: Above ~4 Mbit/s the bucket grows to 4 ms of traffic so the shaper's timer
#: does not have to fire for every single frame.
BURST_SECONDS = 0.004

#: Default tbf queue: 1000 full frames, i.e. what a real NIC queues with
#: Linux's default ``txqueuelen`` of 1000.  Bursty query traffic (nine robots
#: answering the central at once, a ZeroMQ/TCP window) fits without queue
#: drops, which would otherwise confound the loss setting; drops that do
#: happen are reported separately as :attr:`LinkCounters.queue_drops`.
DEFAULT_QUEUE_BYTES = 1000 * ETH_FRAME_MAX

#: Loss is drawn as ``numgen random mod LOSS_SCALE < threshold``: 0.01 % steps.
LOSS_SCALE = 10_000

#: ``LinkSpec.loss_model`` values: independent per-packet loss, or Gilbert bursts.
LOSS_MODELS = ("random", "burst")

class LinkEmulationError(CoapkbError, RuntimeError):
    """Setting up, changing or tearing down the emulated network failed."""


# --------------------------------------------------------------------------
# Link specification and counters
# --------------------------------------------------------------------------


def _check_number(field: str, value: object, *, allow_none: bool = False) -> None:
    if value is None and allow_none:
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"LinkSpec.{field} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise ValueError(f"LinkSpec.{field} must be finite, got {value!r}")


@dataclass(frozen=True)
class LinkSpec:
    """How one host's link behaves (applied to both directions unless noted).

    ``rate_kbit``
        Link rate in kbit/s (1 kbit = 1000 bit, as in ``tc``), counted in
        Ethernet frames without preamble/FCS (UDP payload + 42 bytes for
        IPv4).  ``None`` = unshaped (as fast as veth goes).
    ``loss_pct``
        Percent (0..100, 0.01 % steps) of the packets *this host sends* that
        are lost after having used its link.
    ``delay_ms``
        One-way delay added to packets this host sends, after its shaper
        (the user-space delay line, :mod:`.delayline`).  The RTT between two
        hosts is the sum of both hosts' ``delay_ms``.
    ``queue_bytes``
        Shaper queue limit in bytes; ``None`` = :data:`DEFAULT_QUEUE_BYTES`.
    ``jitter_ms``
        Each packet's delay is ``delay_ms`` plus a uniform draw from
        ``[-jitter_ms, +jitter_ms]``, but never earlier than the host's
        previous packet (no reordering), so ``jitter_ms <= delay_ms``.
    ``loss_model``
        ``"random"``: each packet is lost independently with ``loss_pct``
        (in nftables).  ``"burst"``: Gilbert's two-state model (a Good state
        that loses nothing, a Bad state that loses everything) with mean
        loss ``loss_pct`` and mean run of consecutive losses ``burst_len``
        (in the delay line; see :attr:`gilbert_p`).
    ``burst_len``
        Mean number of consecutive lost packets for ``loss_model="burst"``
        (at least 1); ignored for ``"random"``.
    """

    rate_kbit: float | None = None
    loss_pct: float = 0.0
    delay_ms: float = 0.0
    queue_bytes: int | None = None
    jitter_ms: float = 0.0
    loss_model: str = "random"
    burst_len: float = 3.0

    def __post_init__(self) -> None:
        _check_number("rate_kbit", self.rate_kbit, allow_none=True)
        if self.rate_kbit is not None and not 1.0 <= self.rate_kbit <= 10_000_000:
            raise ValueError(
                f"LinkSpec.rate_kbit must be None (unshaped) or 1..10000000 kbit/s, got {self.rate_kbit!r}"
            )
        _check_number("loss_pct", self.loss_pct)
        if not 0.0 <= self.loss_pct <= 100.0:
            raise ValueError(f"LinkSpec.loss_pct must be within 0..100, got {self.loss_pct!r}")
        _check_number("delay_ms", self.delay_ms)
        if not 0.0 <= self.delay_ms <= 60_000:
            raise ValueError(f"LinkSpec.delay_ms must be within 0..60000, got {self.delay_ms!r}")
        _check_number("jitter_ms", self.jitter_ms)
        if not 0.0 <= self.jitter_ms <= self.delay_ms:
            raise ValueError(
                f"LinkSpec.jitter_ms must be within 0..delay_ms ({self.delay_ms:g}), got {self.jitter_ms!r}"
            )
        if self.loss_model not in LOSS_MODELS:
            raise ValueError(f"LinkSpec.loss_model must be one of {', '.join(LOSS_MODELS)}, got {self.loss_model!r}")
        _check_number("burst_len", self.burst_len)
        if self.burst_len < 1.0:
            raise ValueError(f"LinkSpec.burst_len must be at least 1 packet, got {self.burst_len!r}")
        if self.loss_model == "burst" and self.loss_pct > 0:
            # p = l / (b (1 - l)) is a probability only for b >= l / (1 - l):
            # a high loss rate cannot come in short bursts.
            loss = self.loss_pct / 100
            if loss >= 1.0 or loss / (1 - loss) > self.burst_len:
                shortest = "no burst length" if loss >= 1.0 else f"at least {loss / (1 - loss):.3g}"
                raise ValueError(
                    f"LinkSpec.burst_len {self.burst_len:g} cannot give {self.loss_pct:g} % burst loss "
                    f"({shortest} can)"
                )
        if self.queue_bytes is not None:
            if isinstance(self.queue_bytes, bool) or not isinstance(self.queue_bytes, int):
                raise ValueError(f"LinkSpec.queue_bytes must be an int or None, got {self.queue_bytes!r}")
            if self.queue_bytes < 2 * ETH_FRAME_MAX:
                raise ValueError(
                    f"LinkSpec.queue_bytes must be at least {2 * ETH_FRAME_MAX} (two full frames), "
                    f"got {self.queue_bytes!r}"
                )

    @property
    def rate_bit_s(self) -> int | None:
        """The rate in bit/s as given to ``tc`` (``None`` = unshaped)."""
        return None if self.rate_kbit is None else max(1, round(self.rate_kbit * 1000))

    @property
    def burst_bytes(self) -> int:
        """Token-bucket depth (see :data:`MIN_BURST_BYTES`)."""
        if self.rate_bit_s is None:
            return MIN_BURST_BYTES
        return max(MIN_BURST_BYTES, math.ceil(self.rate_bit_s / 8 * BURST_SECONDS))

    @property
    def limit_bytes(self) -> int:
        """Shaper queue limit in bytes."""
        return DEFAULT_QUEUE_BYTES if self.queue_bytes is None else self.queue_bytes

    @property
    def loss_threshold(self) -> int:
        """``numgen random mod LOSS_SCALE < loss_threshold`` drops a packet."""
        return round(self.loss_pct * LOSS_SCALE / 100)

    @property
    def gilbert_p(self) -> float:
        """Burst loss: probability of going Good -> Bad at a packet.

        With ``r`` = :attr:`gilbert_r`, the Bad state's stationary share (the
        mean loss) is ``p / (p + r)``; solving for ``loss_pct / 100 = l`` gives
        ``p = l * r / (1 - l)``.
        """
        loss = self.loss_pct / 100
        return 0.0 if loss <= 0 else loss * self.gilbert_r / (1 - loss)

    @property
    def gilbert_r(self) -> float:
        """Burst loss: probability of going Bad -> Good at a packet; a stay in
        Bad is geometric with mean ``1 / r`` = :attr:`burst_len` packets."""
        return 1.0 / self.burst_len

    @property
    def needs_delay_line(self) -> bool:
        """Whether this host's packets must pass the user-space delay line."""
        return self.delay_ms > 0 or self.jitter_ms > 0 or (self.loss_model == "burst" and self.loss_pct > 0)

    def __str__(self) -> str:
        rate = "unshaped" if self.rate_kbit is None else f"{self.rate_kbit:g} kbit/s"
        loss = f"{self.loss_pct:g} % loss"
        if self.loss_model == "burst":
            loss += f" in bursts of {self.burst_len:g}"
        extra = ""
        if self.delay_ms:
            extra = f", {self.delay_ms:g} ms delay" + (f" +- {self.jitter_ms:g} ms" if self.jitter_ms else "")
        return f"{rate}, {loss}{extra}"


@dataclass(frozen=True)
class LinkCounters:
    """Traffic on one host's link, counted where the host puts it on the link.

    ``tx_*`` are frames the host's ``eth0`` handed to the link (after its
    uplink shaper, *before* the loss rule, so lost packets are included);
    ``rx_*`` are frames delivered to it.  ``dropped``/``dropped_bytes`` are
    the host's transmitted frames removed by the loss rule; ``queue_drops``
    counts frames the shapers' queues (uplink and downlink) discarded because
    they were full -- it should stay 0 in a benchmark.
    """

    tx_bytes: int = 0
    tx_packets: int = 0
    rx_bytes: int = 0
    rx_packets: int = 0
    dropped: int = 0
    dropped_bytes: int = 0
    queue_drops: int = 0

    def __sub__(self, other: LinkCounters) -> LinkCounters:
        """Difference between two readings (``after - before``)."""
        return LinkCounters(
            self.tx_bytes - other.tx_bytes,
            self.tx_packets - other.tx_packets,
            self.rx_bytes - other.rx_bytes,
            self.rx_packets - other.rx_packets,
            self.dropped - other.dropped,
            self.dropped_bytes - other.dropped_bytes,
            self.queue_drops - other.queue_drops,
        )

