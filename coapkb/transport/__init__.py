"""Communication (the seed's Fig. 2): one interface, three transports.

``open_client`` and ``serve`` pick the implementation from a scheme name
(``coap``, ``zmq``, ``zenoh`` or ``zenoh+udp``), so nothing above this
package names a transport.
"""

from __future__ import annotations

from typing import Any

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

SCHEMES = ("coap", "zmq", "zenoh", "zenoh+udp")


def reliability_for(scheme: str, profile: str = "robust", *, link_kbps: float | None = None) -> Any:
    """What a robot hands to both :func:`open_client` and :func:`serve` as
    ``retransmission``: for CoAP's ``robust`` profile one shared layer (its
    server's notifications then use its client's path estimates), else the
    profile name.  TCP retransmits by itself: ZeroMQ ignores it."""
    if scheme == "coap":
        from .coap.reliability import make_reliability

        return make_reliability(profile, link_kbps=link_kbps)
    return profile


async def open_client(scheme: str, *, retransmission: Any = "robust", security: Any = None) -> ClientTransport:
    """A client transport for ``scheme``.

    ``retransmission``: a reliability profile name (``robust``, the default,
    or one of the CON profiles ``rfc7252``, ``lossy-fixed``, ``adaptive``),
    or what :func:`reliability_for` returned; ZeroMQ and Zenoh ignore it.
    ``security``: a :class:`coapkb.security.coap.ClientSecurity` (CoAP:
    OSCORE keyed by EDHOC), :class:`coapkb.security.curve.ZmqClientSecurity`
    (ZeroMQ: CurveZMQ), :class:`coapkb.security.zenoh_tls.ZenohClientSecurity`
    (Zenoh: mTLS; ``zenoh+udp`` cannot be secured), or None."""
    if scheme == "coap":
        from .coap import CoapClientTransport

        return await CoapClientTransport.create(retransmission=retransmission, security=security)
    if scheme == "zmq":
        from .zmq.transport import ZmqClientTransport

        return ZmqClientTransport(security=security)
    if scheme in ("zenoh", "zenoh+udp"):
        from .zenoh.transport import ZenohClientTransport

        return ZenohClientTransport(security=security)
    raise ValueError(f"unknown transport {scheme!r} (choose from {', '.join(SCHEMES)})")


async def serve(
    service: Service, endpoint: Endpoint, *, retransmission: Any = "robust", security: Any = None
) -> ServerTransport:
    """Expose ``service`` on ``endpoint`` (its scheme picks the transport).
    ``retransmission`` applies to CoAP's confirmable notifications;
    ``security`` is a :class:`coapkb.security.coap.ServerSecurity` (CoAP) or
    :class:`coapkb.security.curve.ZmqServerSecurity` (ZeroMQ) or
    :class:`coapkb.security.zenoh_tls.ZenohServerSecurity` (Zenoh), or None."""
    if endpoint.scheme == "coap":
        from .coap import CoapServerTransport

        return await CoapServerTransport.start(service, endpoint, retransmission=retransmission, security=security)
    if endpoint.scheme == "zmq":
        from .zmq.transport import ZmqServerTransport

        return await ZmqServerTransport.start(service, endpoint, security=security)
    if endpoint.scheme in ("zenoh", "zenoh+udp"):
        from .zenoh.transport import ZenohServerTransport

        return await ZenohServerTransport.start(service, endpoint, security=security)
    raise ValueError(f"unknown transport {endpoint.scheme!r} (choose from {', '.join(SCHEMES)})")


__all__ = [
    "ClientTransport",
    "Endpoint",
    "PeerUnreachable",
    "ResourceInfo",
    "ServerTransport",
    "Service",
    "TrafficCounters",
    "TransportError",
    "open_client",
    "reliability_for",
    "serve",
]
