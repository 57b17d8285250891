"""Communication (the seed's Fig. 2): one interface, several transports.

``open_client`` and ``serve`` pick the implementation the
:mod:`.registry` holds for a scheme (``coap``, ``zmq``, ``zenoh``,
``zenoh+udp``, ``zenoh+quic`` or ``dds``), so nothing above this package names a
transport.  Security
plugs in from above through the seams of :mod:`.security`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from .base import (
    ClientTransport,
    Endpoint,
    PeerGone,
    PeerTimeout,
    PeerUnreachable,
    ResourceInfo,
    ServerTransport,
    Service,
    TrafficCounters,
    TransportError,
)
from .registry import SCHEMES, Reliability, TransportInfo, parse_endpoint, secured_schemes, transport_for
from .security import ClientSecurity, GuardedService, ServerSecurity


def reliability_for(scheme: str, *, link_kbps: float | None = None,
                    options: Mapping[str, Any] | None = None) -> Reliability | None:
    """The reliability layer a robot hands to both :func:`open_client` and
    :func:`serve`: for CoAP one shared layer (its server's notifications
    then use its client's path estimates), sized for a link of
    ``link_kbps`` if known and tuned by ``options`` (the robot's
    ``[transport.coap]`` table; ValueError naming a field it cannot
    take); None for a transport without one (TCP, QUIC or RTPS
    retransmits by itself: its table goes to :func:`open_client` and
    :func:`serve` instead)."""
    make = transport_for(scheme).reliability
    return None if make is None else make(link_kbps, options or {})


def check_table(scheme: str, table: Mapping[str, Any]) -> None:
    """ValueError naming the field of a ``[transport.SCHEME]`` table that
    ``scheme``'s transport cannot take (``FIELD: why``), or saying that it
    takes none; an unknown scheme raises :class:`UnknownTransport`."""
    info = transport_for(scheme)
    if info.reliability is not None:
        info.reliability(None, table)
    elif info.options is not None:
        info.options(table)
    elif table:
        raise ValueError(f"{sorted(table)[0]}: unknown field ({scheme} has no tunables)")


async def open_client(scheme: str, *, reliability: Reliability | None = None,
                      security: ClientSecurity | None = None,
                      options: Mapping[str, Any] | None = None) -> ClientTransport:
    """A client transport for ``scheme``.

    ``reliability``: what :func:`reliability_for` returned, or None for a
    layer of the transport's own; transports without one (ZeroMQ, Zenoh,
    DDS) ignore it.  ``security``: the client side of the transport's
    security mechanism (:func:`coapkb.security.client_security`), or None.
    ``options``: the robot's ``[transport.SCHEME]`` table (:func:`check_table`),
    for a transport without a reliability layer."""
    return await transport_for(scheme).open_client(reliability, security, options or {})


async def serve(
    service: Service, endpoint: Endpoint, *, reliability: Reliability | None = None,
    security: ServerSecurity | None = None, options: Mapping[str, Any] | None = None,
) -> ServerTransport:
    """Expose ``service`` on ``endpoint`` (its scheme picks the transport).
    ``reliability`` times CoAP's confirmable notifications (None: a layer
    of the server's own); ``security`` is the server side of the
    transport's security mechanism (:func:`coapkb.security.server_security`),
    or None; ``options`` as for :func:`open_client`.  With security every
    request is held to its access rules before the service sees it."""
    serves = transport_for(endpoint.scheme).serve
    if security is not None:
        service = GuardedService(service, security.rules)
    return await serves(service, endpoint, reliability, security, options or {})


__all__ = [
    "SCHEMES",
    "ClientSecurity",
    "ClientTransport",
    "Endpoint",
    "PeerGone",
    "PeerTimeout",
    "PeerUnreachable",
    "Reliability",
    "ResourceInfo",
    "ServerSecurity",
    "ServerTransport",
    "Service",
    "TrafficCounters",
    "TransportError",
    "TransportInfo",
    "check_table",
    "open_client",
    "parse_endpoint",
    "reliability_for",
    "secured_schemes",
    "serve",
    "transport_for",
]
