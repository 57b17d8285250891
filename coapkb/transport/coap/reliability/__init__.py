"""Reliability for CoAP over lossy links: how and when a request is retried.

* :mod:`.layer`: the default for robots (``robust``): every try a fresh
  exchange, RFC 6298 timeouts over unambiguous samples, a window of
  exchanges in flight per peer, hedged copies when the path loses much.
  :mod:`.notifications` times the server's CON notifications from it.
* :mod:`.rto` and :mod:`.cocoa_hooks`: the earlier profiles, kept for
  comparison: ``rfc7252`` (RFC 7252's defaults), ``lossy-fixed`` (short
  fixed timeouts, capped backoff) and ``adaptive`` (CoCoA-style RTO per peer,
  on aiocoap's CON retransmission).
"""

from __future__ import annotations

from .layer import ReliabilityLayer, ReliabilitySettings
from .rto import PROFILES as CON_PROFILES

#: The layer's profile name.
ROBUST = "robust"
#: Every selectable reliability profile; the first is the default.
PROFILE_NAMES: tuple[str, ...] = (ROBUST, *CON_PROFILES)
DEFAULT_PROFILE = ROBUST


def make_reliability(profile: str, *, link_kbps: float | None = None) -> "ReliabilityLayer | str":
    """What to hand to a CoAP client and server of one robot: one shared
    layer for ``robust`` (so the server's notifications use the client's
    estimates), else the profile's name."""
    if profile == ROBUST:
        return ReliabilityLayer(ReliabilitySettings(link_kbps=link_kbps))
    if profile not in CON_PROFILES:
        raise ValueError(f"unknown reliability profile {profile!r} (choose from {', '.join(PROFILE_NAMES)})")
    return profile


__all__ = ["PROFILE_NAMES", "DEFAULT_PROFILE", "ROBUST", "ReliabilityLayer", "ReliabilitySettings", "make_reliability"]
