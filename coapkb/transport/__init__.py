"""Communication (the seed's Fig. 2): one interface, several transports.

``open_client`` and ``serve`` pick the implementation the
:mod:`.registry` holds for a scheme (``coap``, ``zmq``, ``zenoh`` or
``zenoh+udp``), so nothing above this package names a transport.  Security
plugs in from above through the seams of :mod:`.security`.
"""

from __future__ import annotations

from .base import (
    ClientTransport,
    Endpoint,
    PeerUnreachable,
    ResourceInfo,
    ServerTransport,
    Service,
    TrafficCounters,
    TransportError,
)
from .registry import SCHEMES, TransportInfo, secured_schemes, transport_for
from .security import ClientSecurity, GuardedService, ServerSecurity


def reliability_for(scheme: str, profile: str = "robust", *, link_kbps: float | None = None) -> object:
    """What a robot hands to both :func:`open_client` and :func:`serve` as
    ``retransmission``: for CoAP's ``robust`` profile one shared layer (its
    server's notifications then use its client's path estimates), else the
    profile name.  TCP retransmits by itself: ZeroMQ ignores it."""
    make = transport_for(scheme).reliability
    return profile if make is None else make(profile, link_kbps)


async def open_client(scheme: str, *, retransmission: object = "robust",
                      security: ClientSecurity | None = None) -> ClientTransport:
    """A client transport for ``scheme``.

    ``retransmission``: a reliability profile name (``robust``, the default,
    or one of the CON profiles ``rfc7252``, ``lossy-fixed``, ``adaptive``),
    or what :func:`reliability_for` returned; ZeroMQ and Zenoh ignore it.
    ``security``: the client side of the transport's security mechanism
    (:func:`coapkb.security.client_security`), or None."""
    return await transport_for(scheme).open_client(retransmission, security)


async def serve(
    service: Service, endpoint: Endpoint, *, retransmission: object = "robust", security: ServerSecurity | None = None
) -> ServerTransport:
    """Expose ``service`` on ``endpoint`` (its scheme picks the transport).
    ``retransmission`` applies to CoAP's confirmable notifications;
    ``security`` is the server side of the transport's security mechanism
    (:func:`coapkb.security.server_security`), or None.  With security every
    request is held to its access rules before the service sees it."""
    serves = transport_for(endpoint.scheme).serve
    if security is not None:
        service = GuardedService(service, security.rules)
    return await serves(service, endpoint, retransmission, security)


__all__ = [
    "SCHEMES",
    "ClientTransport",
    "Endpoint",
    "PeerUnreachable",
    "ResourceInfo",
    "ServerTransport",
    "Service",
    "TrafficCounters",
    "TransportError",
    "TransportInfo",
    "open_client",
    "reliability_for",
    "secured_schemes",
    "serve",
    "transport_for",
]
