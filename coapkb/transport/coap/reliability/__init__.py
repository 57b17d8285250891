"""Reliability for CoAP over lossy links: how and when a request is retried.

:mod:`.layer` (``robust``): every try a fresh exchange, RFC 6298 timeouts
over unambiguous samples, a window of exchanges in flight per peer, hedged
copies when the path loses much.  :mod:`.notifications` times the server's
CON notifications from it.  The CON profiles it was measured against
(``rfc7252``, ``lossy-fixed``, CoCoA ``adaptive``) were retired; their
measurements stay in ``experiments/results/`` (docs/retransmission.md).
"""

from __future__ import annotations

from .layer import ReliabilityLayer, ReliabilitySettings

#: The layer's name, as records state it (its stats, the bench's
#: ``retransmission_profile`` column).
ROBUST = ReliabilityLayer.name


def make_reliability(*, link_kbps: float | None = None) -> ReliabilityLayer:
    """The layer for one robot's CoAP client and server: shared, so the
    server's notifications use the client's estimates."""
    return ReliabilityLayer(ReliabilitySettings(link_kbps=link_kbps))


__all__ = ["ROBUST", "ReliabilityLayer", "ReliabilitySettings", "make_reliability"]
