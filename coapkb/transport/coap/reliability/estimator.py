"""Estimators of one path to a peer, fed only with unambiguous samples.

Pure arithmetic, no I/O: the layer (:mod:`.layer`) measures, these keep score.

* The round trip itself is :class:`coapkb.transport.rtt.RttEstimator`
  (RFC 6298), shared with the agents' liveness requests.
* :func:`airtime` and :class:`UplinkQueue`: how long bytes take on the
  robot's link, so a timeout covers the airtime of *this* exchange.
* :class:`LossEstimator` is the share of attempts that went unanswered
  (request or answer lost), an exponentially weighted average.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: IPv4 + UDP header bytes per datagram (the link carries them too).
IP_UDP_OVERHEAD = 28


def airtime(nbytes: float, link_bps: float | None) -> float:
    """Seconds to serialise ``nbytes`` of CoAP (plus IP/UDP headers) at ``link_bps``."""
    if not link_bps:
        return 0.0
    return (nbytes + IP_UDP_OVERHEAD) * 8.0 / link_bps


@dataclass
class UplinkQueue:
    """When the datagrams a host sends leave its own link, at ``link_bps``.

    Every datagram the robot sends (its client's and its server's) takes its
    airtime on the link after the ones before it; a timeout must start when
    the datagram leaves, not when it was handed to the socket.  Shapers
    with a burst allowance send faster at first, so this errs long."""

    link_bps: float | None
    free_at: float = 0.0

    def on_sent(self, nbytes: int, now: float) -> None:
        if self.link_bps:
            self.free_at = max(self.free_at, now) + airtime(nbytes, self.link_bps)

    def wait(self, now: float) -> float:
        """Seconds until what is queued now has left the link."""
        return max(0.0, self.free_at - now)


@dataclass
class LossEstimator:
    """Share of attempts lost on the round trip, averaged with weight ``gain``
    (1/16: about the last 16 attempts count)."""

    gain: float = 1 / 16
    rate: float = 0.0
    observed: int = 0

    def on_outcome(self, lost: bool) -> None:
        # The first observations are averaged plainly, so a few early losses
        # are not diluted by a made-up prior of zero.
        self.observed += 1
        weight = max(self.gain, 1.0 / self.observed)
        self.rate += weight * ((1.0 if lost else 0.0) - self.rate)

    def one_way(self) -> float:
        """The loss per direction that would give this round-trip loss,
        assuming both directions alike: 1 - sqrt(1 - p)."""
        return 1.0 - math.sqrt(max(0.0, 1.0 - self.rate))
