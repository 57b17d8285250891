"""Each transport's security, built from a member's identity and the team's
trust: the one place that turns a transport into its mechanism.

The transport registry (:mod:`coapkb.transport.registry`) names the
mechanism protecting each scheme; this module builds its client and server
sides.  Each mechanism's module is imported when it is built: a ZeroMQ
robot never loads aiocoap's OSCORE stack, a CoAP one never loads Zenoh.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from ..transport import secured_schemes, transport_for
from ..transport.security import ClientSecurity, ServerSecurity
from .errors import SecurityError
from .keys import TeamIdentity
from .policy import AccessPolicy

#: Which member serves at an endpoint (``host:port`` -> name), where known.
Expected = dict[str, str]


@dataclass(frozen=True)
class Mechanism:
    """How one security mechanism is built."""

    #: What it is, for messages.
    title: str
    client: Callable[[TeamIdentity, Expected | None], ClientSecurity]
    server: Callable[[TeamIdentity, AccessPolicy], ServerSecurity]
    #: A client must know which member serves an endpoint before it connects
    #: (CurveZMQ needs the server's public key); the others learn it in the
    #: handshake, and check it only where it is known.
    needs_server_name: bool = False


def _oscore_client(identity: TeamIdentity, expected: Expected | None) -> ClientSecurity:
    from .coap import ClientSecurity as OscoreClient

    return OscoreClient(identity, expected)


def _oscore_server(identity: TeamIdentity, policy: AccessPolicy) -> ServerSecurity:
    from .coap import ServerSecurity as OscoreServer

    return OscoreServer(identity, policy)


def _curve_client(identity: TeamIdentity, expected: Expected | None) -> ClientSecurity:
    from .curve import ZmqClientSecurity

    return ZmqClientSecurity(identity, dict(expected or {}))


def _curve_server(identity: TeamIdentity, policy: AccessPolicy) -> ServerSecurity:
    from .curve import ZmqServerSecurity

    return ZmqServerSecurity(identity, policy)


def _tls_client(identity: TeamIdentity, expected: Expected | None) -> ClientSecurity:
    from .zenoh_tls import ZenohClientSecurity

    return ZenohClientSecurity(identity, expected)


def _tls_server(identity: TeamIdentity, policy: AccessPolicy) -> ServerSecurity:
    from .zenoh_tls import ZenohServerSecurity

    return ZenohServerSecurity(identity, policy)


#: By the names the transport registry uses.
MECHANISMS: dict[str, Mechanism] = {
    "oscore": Mechanism("OSCORE keyed by EDHOC", _oscore_client, _oscore_server),
    "curve": Mechanism("CurveZMQ", _curve_client, _curve_server, needs_server_name=True),
    "tls": Mechanism("mutual TLS with team certificates", _tls_client, _tls_server),
}


def mechanism_for(scheme: str) -> Mechanism:
    """The mechanism securing transport ``scheme``; :class:`SecurityError` if it cannot be secured."""
    transport = transport_for(scheme)
    if transport.security is None:
        why = f": {transport.unsecurable_because}" if transport.unsecurable_because else ""
        raise SecurityError(f"the {scheme} transport cannot be secured{why} (use {', '.join(secured_schemes())})")
    return MECHANISMS[transport.security]


def client_security(scheme: str, identity: TeamIdentity, expected: Expected | None = None) -> ClientSecurity:
    """``identity``'s client side over ``scheme``; ``expected`` names the
    member that must answer at an endpoint (each endpoint not named accepts
    any member, where the mechanism allows)."""
    return mechanism_for(scheme).client(identity, expected)


def server_security(scheme: str, identity: TeamIdentity, policy: AccessPolicy | None = None) -> ServerSecurity:
    """``identity``'s server side over ``scheme``, holding requests to ``policy`` (default: the team's)."""
    return mechanism_for(scheme).server(identity, policy if policy is not None else AccessPolicy())
