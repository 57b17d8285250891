"""Communication (the seed's Fig. 2): one interface, two transports.

``open_client`` and ``serve`` pick the implementation from a scheme name
(``coap`` or ``zmq``), so nothing above this package names a transport.
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

SCHEMES = ("coap", "zmq")


async def open_client(scheme: str, *, retransmission: Any = "adaptive") -> ClientTransport:
    """A client transport for ``scheme``.

    ``retransmission`` (a profile name or profile) sets CoAP's confirmable
    retransmission; TCP retransmits by itself, so ZeroMQ ignores it."""
    if scheme == "coap":
        from .coap.transport import CoapClientTransport

        return await CoapClientTransport.create(retransmission=retransmission)
    if scheme == "zmq":
        from .zmq.transport import ZmqClientTransport

        return ZmqClientTransport()
    raise ValueError(f"unknown transport {scheme!r} (choose from {', '.join(SCHEMES)})")


async def serve(service: Service, endpoint: Endpoint, *, retransmission: Any = "adaptive") -> ServerTransport:
    """Expose ``service`` on ``endpoint`` (its scheme picks the transport).
    ``retransmission`` applies to CoAP's confirmable notifications."""
    if endpoint.scheme == "coap":
        from .coap.transport import CoapServerTransport

        return await CoapServerTransport.start(service, endpoint, retransmission=retransmission)
    if endpoint.scheme == "zmq":
        from .zmq.transport import ZmqServerTransport

        return await ZmqServerTransport.start(service, endpoint)
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
    "serve",
]
