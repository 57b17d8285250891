"""The round-trip estimator of RFC 6298 section 2, for anything that times
requests: the CoAP reliability layer (per peer) and the agents' liveness
requests.  Pure arithmetic: callers measure, and each turns the estimate
into its own timeout."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class RttEstimator:
    """Smoothed round trip (SRTT) and its variation (RTTVAR), with RFC 6298's
    gains alpha 1/8 and beta 1/4; the first sample sets SRTT to itself and
    RTTVAR to half of it."""

    alpha: float = 0.125
    beta: float = 0.25
    srtt: float | None = None
    rttvar: float = 0.0
    min_rtt: float | None = None
    samples: int = 0

    def on_sample(self, rtt: float) -> None:
        rtt = max(rtt, 0.0)
        if self.srtt is None:
            self.srtt, self.rttvar = rtt, rtt / 2
        else:
            self.rttvar = (1 - self.beta) * self.rttvar + self.beta * abs(self.srtt - rtt)
            self.srtt = (1 - self.alpha) * self.srtt + self.alpha * rtt
        self.min_rtt = rtt if self.min_rtt is None else min(self.min_rtt, rtt)
        self.samples += 1

    def rto(self, *, k: float, granularity: float, floor: float, ceiling: float, initial: float) -> float:
        """SRTT + max(G, K*RTTVAR), within [floor, ceiling]; ``initial`` before any sample."""
        if self.srtt is None:
            return initial
        return min(ceiling, max(floor, self.srtt + max(granularity, k * self.rttvar)))
