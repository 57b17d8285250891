"""Reliability for CoAP over lossy links: how and when a request is retried.

:mod:`.layer` (``robust``): every try a fresh exchange, RFC 6298 timeouts
over unambiguous samples, a window of exchanges in flight per peer, hedged
copies when the path loses much.  :mod:`.notifications` times the server's
CON notifications from it.  The CON profiles it was measured against
(``rfc7252``, ``lossy-fixed``, CoCoA ``adaptive``) were retired; what they
measured: docs/reports/2026-11-22-con-retransmission-profiles.md.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from ....typed_fields import typed_fields
from .layer import ReliabilityLayer, ReliabilitySettings

#: The layer's name, as records state it (its stats, the bench's
#: ``retransmission_profile`` column).
ROBUST = ReliabilityLayer.name


#: The settings a robot's ``[transport.coap]`` table may set: every policy
#: knob but the link rate (the top-level ``link_kbps``).
TUNABLES = tuple(f.name for f in dataclasses.fields(ReliabilitySettings) if f.name != "link_kbps")


def settings_from(options: Mapping[str, Any], *, link_kbps: float | None = None) -> ReliabilitySettings:
    """Settings from a ``[transport.coap]`` table (``options``: tunable ->
    value, each of its default's type; an int stands for a float).  Raises
    ValueError naming the first field that is unknown, of the wrong type, or
    out of range together with the rest."""
    return ReliabilitySettings(link_kbps=link_kbps, **typed_fields(ReliabilitySettings, options, TUNABLES))


def make_reliability(*, link_kbps: float | None = None, options: Mapping[str, Any] | None = None) -> ReliabilityLayer:
    """The layer for one robot's CoAP client and server: shared, so the
    server's notifications use the client's estimates.  ``options``: the
    robot's ``[transport.coap]`` table (:func:`settings_from`)."""
    return ReliabilityLayer(settings_from(options or {}, link_kbps=link_kbps))


__all__ = ["ROBUST", "TUNABLES", "ReliabilityLayer", "ReliabilitySettings", "make_reliability", "settings_from"]
