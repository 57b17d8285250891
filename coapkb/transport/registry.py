"""Which transports there are, and what each provides.

Every transport registers here once: its URI scheme, how to open its
client and start its server, its reliability layer (CoAP's, shared by a
robot's client and server; a TCP transport needs none), the security
mechanism that protects it, and what it can carry besides coapkb's own
resources.  Everything above this package asks the registry instead of
comparing scheme names, so adding a transport is one folder plus one
entry in :data:`REGISTERED`.

The factories import their transport when called: choosing ZeroMQ never
loads aiocoap or Zenoh, and ``import coapkb.transport`` loads none of them.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, cast

from ..errors import CoapkbError
from ..typed_fields import typed_fields
from .base import Endpoint

if TYPE_CHECKING:
    from .base import ClientTransport, ServerTransport, Service
    from .coap.reliability import ReliabilityLayer
    from .dds.transport import DdsOptions
    from .security import ClientSecurity, ServerSecurity
    from .zenoh.transport import ZenohOptions
    from .zmq.transport import ZmqOptions


class Reliability(Protocol):
    """A transport's reliability layer (CoAP's
    :class:`~.coap.reliability.ReliabilityLayer`), built by
    :attr:`TransportInfo.reliability` and shared by a robot's client and
    server; only the transport that built it looks inside."""

    def as_dict(self) -> dict[str, Any]:
        """Its settings and per-peer estimates, for the robot's record."""
        ...

    @property
    def confirm_every(self) -> int:
        """Of an observation's notifications, every this many is confirmable (1: all)."""
        ...


#: A robot's ``[transport.SCHEME]`` table, as read from its TOML.
Table = Mapping[str, Any]
#: ``open_client``'s signature for one transport: (reliability, security, table).
ClientFactory = Callable[["Reliability | None", "ClientSecurity | None", Table], Awaitable["ClientTransport"]]
#: ``serve``'s signature for one transport: (service, endpoint, reliability, security, table).
ServerFactory = Callable[["Service", "Endpoint", "Reliability | None", "ServerSecurity | None", Table],
                         Awaitable["ServerTransport"]]
#: Builds the reliability a robot's client and server share, from its link
#: rate in kbit/s (None: unknown) and its ``[transport.SCHEME]`` table
#: (ValueError naming a field it cannot take).
ReliabilityFactory = Callable[["float | None", Table], Reliability]
#: Builds the options record of a transport without a reliability layer
#: from its ``[transport.SCHEME]`` table (ValueError naming a field).
OptionsFactory = Callable[[Table], object]


class UnknownTransport(CoapkbError, ValueError):
    """A scheme no transport registered."""


@dataclass(frozen=True)
class TransportInfo:
    """One registered transport."""

    scheme: str
    #: Listens on UDP (datagrams); else on TCP (a byte stream).
    datagram: bool
    #: The port it usually listens on.
    default_port: int
    open_client: ClientFactory
    serve: ServerFactory
    #: Builds the reliability layer a robot hands to both its client and its
    #: server; None: the transport has none of its own to share.
    reliability: ReliabilityFactory | None = None
    #: Builds its options from a robot's ``[transport.SCHEME]`` table (a
    #: transport with a reliability layer gives the table to the layer);
    #: None: it has no tunables.
    options: OptionsFactory | None = None
    #: The security mechanism protecting it (a name :mod:`coapkb.security`
    #: implements: ``oscore``, ``curve``, ``tls``); None: it cannot be secured.
    security: str | None = None
    #: Speaks the CoRE Resource Directory (RFC 9176, a CoAP interface).
    resource_directory: bool = False
    #: Other spellings of the scheme accepted in URIs.
    aliases: tuple[str, ...] = ()
    #: What below coapkb recovers its lost packets: ``tcp`` (the kernel's TCP),
    #: ``quic`` (a QUIC stack inside the transport's library), ``rtps`` (DDS's
    #: reliable QoS: heartbeats, ACKNACKs, retransmits); None: nothing
    #: does, unless its own :attr:`reliability` layer.
    recovery: str | None = None
    #: Why it cannot be secured (``security`` None), for the refusal a user gets.
    unsecurable_because: str | None = None

    @property
    def retransmits_itself(self) -> bool:
        """The protocol below (TCP, QUIC, RTPS) retransmits: it takes no reliability layer."""
        return self.recovery is not None


# ----------------------------------------------------------------- the factories


# CoAP's factories are handed what _coap_reliability built (or None), so the
# casts hold.
async def _coap_client(reliability: Reliability | None, security: ClientSecurity | None,
                       table: Table) -> ClientTransport:
    from .coap import CoapClientTransport

    layer = cast("ReliabilityLayer | None", reliability)
    return await CoapClientTransport.create(reliability=layer, security=security)


async def _coap_server(service: Service, endpoint: Endpoint, reliability: Reliability | None,
                       security: ServerSecurity | None, table: Table) -> ServerTransport:
    from .coap import CoapServerTransport

    layer = cast("ReliabilityLayer | None", reliability)
    return await CoapServerTransport.start(service, endpoint, reliability=layer, security=security)


def _coap_reliability(link_kbps: float | None, table: Table) -> Reliability:
    from .coap.reliability import make_reliability

    return make_reliability(link_kbps=link_kbps, options=table)


# The transports built on the core (transport/core.py): their options
# records come from the table; the CoAP layer's table is its own.
def _zmq_options(table: Table) -> ZmqOptions:
    from .zmq.transport import ZmqOptions

    return ZmqOptions(**typed_fields(ZmqOptions, table))


def _zenoh_options(table: Table) -> ZenohOptions:
    from .zenoh.transport import ZenohOptions

    return ZenohOptions(**typed_fields(ZenohOptions, table))


def _dds_options(table: Table) -> DdsOptions:
    from .dds.transport import DdsOptions

    return DdsOptions(**typed_fields(DdsOptions, table, settable=_DDS_TABLE_FIELDS))


#: DdsOptions's fields a table may set (its domain settings are a record of their own).
_DDS_TABLE_FIELDS = frozenset({
    "max_concurrent_requests", "max_observations", "max_clients", "observe_queue", "observe_timeout_s",
    "rediscover_first_s", "rediscover_max_s", "malformed_log_interval_s", "history_depth",
})


async def _zmq_client(reliability: Reliability | None, security: ClientSecurity | None,
                      table: Table) -> ClientTransport:
    from .zmq.transport import ZmqClientTransport

    return ZmqClientTransport(security=security, options=_zmq_options(table))


async def _zmq_server(service: Service, endpoint: Endpoint, reliability: Reliability | None,
                      security: ServerSecurity | None, table: Table) -> ServerTransport:
    from .zmq.transport import ZmqServerTransport

    return await ZmqServerTransport.start(service, endpoint, security=security, options=_zmq_options(table))


async def _zenoh_client(reliability: Reliability | None, security: ClientSecurity | None,
                        table: Table) -> ClientTransport:
    from .zenoh.transport import ZenohClientTransport

    return ZenohClientTransport(security=security, options=_zenoh_options(table))


async def _zenoh_server(service: Service, endpoint: Endpoint, reliability: Reliability | None,
                        security: ServerSecurity | None, table: Table) -> ServerTransport:
    from .zenoh.transport import ZenohServerTransport

    return await ZenohServerTransport.start(service, endpoint, security=security, options=_zenoh_options(table))


async def _dds_client(reliability: Reliability | None, security: ClientSecurity | None,
                      table: Table) -> ClientTransport:
    from .dds.transport import DdsClientTransport

    return DdsClientTransport(options=_dds_options(table))


async def _dds_server(service: Service, endpoint: Endpoint, reliability: Reliability | None,
                      security: ServerSecurity | None, table: Table) -> ServerTransport:
    from .dds.transport import DdsServerTransport

    return await DdsServerTransport.start(service, endpoint, options=_dds_options(table))


# ----------------------------------------------------------------- the registrations

REGISTERED: tuple[TransportInfo, ...] = (
    # CoAP over UDP (aiocoap), the primary transport.
    TransportInfo("coap", datagram=True, default_port=5683, open_client=_coap_client, serve=_coap_server,
                  reliability=_coap_reliability, security="oscore", resource_directory=True),
    # ZeroMQ over TCP, the seed's transport.
    TransportInfo("zmq", datagram=False, default_port=5555, open_client=_zmq_client, serve=_zmq_server,
                  options=_zmq_options, security="curve", aliases=("tcp",), recovery="tcp"),
    # Zenoh over TCP.
    TransportInfo("zenoh", datagram=False, default_port=7447, open_client=_zenoh_client, serve=_zenoh_server,
                  options=_zenoh_options, security="tls", recovery="tcp"),
    # Zenoh's reliable UDP: QUIC streams without TLS, so nothing to secure it with
    # (and no DTLS link exists in Zenoh 1.x).
    TransportInfo("zenoh+udp", datagram=True, default_port=7447, open_client=_zenoh_client, serve=_zenoh_server,
                  options=_zenoh_options, recovery="quic",
                  unsecurable_because="it is Zenoh's reliable UDP, QUIC without encryption or authentication, "
                  "and Zenoh has no DTLS"),
    # Zenoh over QUIC: TLS 1.3 in its handshake, mutual with the team's certificates.
    TransportInfo("zenoh+quic", datagram=True, default_port=7447, open_client=_zenoh_client, serve=_zenoh_server,
                  options=_zenoh_options, security="tls", recovery="quic"),
    # DDS (Cyclone DDS): RTPS over UDP, whose reliable QoS retransmits (heartbeats
    # and ACKNACKs); the PyPI wheel has no DDS Security plugins.
    TransportInfo("dds", datagram=True, default_port=7400, open_client=_dds_client, serve=_dds_server,
                  options=_dds_options, recovery="rtps",
                  unsecurable_because="the cyclonedds wheel carries no DDS Security plugins "
                  "(authentication, access control, cryptography), so DDS runs only --insecure"),
)

#: The registered schemes, in registration order.
SCHEMES: tuple[str, ...] = tuple(t.scheme for t in REGISTERED)
_BY_SCHEME = {name: t for t in REGISTERED for name in (t.scheme, *t.aliases)}


def find(scheme: str) -> TransportInfo | None:
    """The transport registered for ``scheme`` (or one of its aliases), None if there is none."""
    return _BY_SCHEME.get(scheme)


def transport_for(scheme: str) -> TransportInfo:
    """The transport registered for ``scheme`` (or one of its aliases)."""
    found = _BY_SCHEME.get(scheme)
    if found is None:
        raise UnknownTransport(f"unknown transport {scheme!r} (choose from {', '.join(SCHEMES)})")
    return found


def canonical_scheme(scheme: str) -> str:
    """``scheme`` as registered (an alias such as ``tcp`` becomes ``zmq``); an unknown one unchanged."""
    found = _BY_SCHEME.get(scheme)
    return scheme if found is None else found.scheme


def parse_endpoint(uri: str, default_scheme: str = "coap") -> Endpoint:
    """Parse ``coap://h:p``, ``zmq://h:p``, ``tcp://h:p`` (= zmq), ``zenoh://h:p``,
    ``zenoh+udp://h:p``, ``zenoh+quic://h:p``, ``dds://h:p`` or bare ``h:p``
    (in ``default_scheme``); ValueError for a scheme not registered here or
    no ``HOST:PORT``."""
    scheme, sep, rest = uri.partition("://")
    if not sep:
        scheme, rest = default_scheme, uri
    scheme = canonical_scheme(scheme)
    if scheme not in SCHEMES:
        raise ValueError(f"unsupported scheme {scheme!r} in {uri!r} (use {', '.join(s + '://' for s in SCHEMES)})")
    rest = rest.split("/", 1)[0]
    bracketed = rest.startswith("[")
    if bracketed:  # [IPv6]:port
        host, _, port = rest[1:].partition("]:")
    else:
        host, _, port = rest.rpartition(":")
    if not host or not (port.isascii() and port.isdigit()):
        raise ValueError(f"expected HOST:PORT in {uri!r}")
    if int(port) > 65535:
        raise ValueError(f"port {int(port)} out of range (0-65535) in {uri!r}")
    # A host str() could not write back (brackets in it, or a colon outside them).
    if "[" in host or "]" in host or ":" in host and not bracketed:
        raise ValueError(f"expected HOST:PORT in {uri!r} (an IPv6 address in brackets: [::1]:5683)")
    return Endpoint(scheme, host, int(port))


def secured_schemes() -> tuple[str, ...]:
    """The schemes a security mechanism protects."""
    return tuple(t.scheme for t in REGISTERED if t.security is not None)
