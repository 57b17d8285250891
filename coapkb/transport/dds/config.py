"""How a ``dds://HOST:PORT`` endpoint becomes a Cyclone DDS domain.

Pure functions (no Cyclone import), so the mapping can be tested and read
on its own; :mod:`.transport` hands the XML to ``cyclonedds.domain.Domain``.

A server's participant takes all its RTPS traffic, discovery and data, on
the one port ``HOST:PORT`` (:func:`server_domain_xml`: base port ``PORT``,
gains, offsets and participant index 0); a client's participant takes an
ephemeral port and has that server as its only configured peer, pinged for
ever (:func:`client_domain_xml`).  Multicast is off, every domain uses
external domain id 0 on the wire, and :class:`DomainSettings` holds the
slow-radio settings (heartbeat, lease, one Ethernet frame per datagram).

docs/dds.md specifies the addressing, discovery and those settings, with
their reasons.
"""

from __future__ import annotations

import re
import socket
from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

__all__ = ["DomainSettings", "client_domain_xml", "local_address_towards", "server_domain_xml", "topic_names"]


@dataclass(frozen=True)
class DomainSettings:
    """What every coapkb domain sets the same way."""

    #: The DDS domain id on the wire (all of a team's participants share it).
    domain_id: int = 0
    #: Largest UDP payload Cyclone generates: 1500-byte MTU less IPv4 and UDP headers.
    max_message_size: int = 1472
    #: Participant lease: a peer silent this long is dropped.  Cyclone's
    #: default is 10 s, with an SPDP announcement every 8 s; at 30 s one goes
    #: every 28 s (any packet from a peer renews its lease meanwhile).  A
    #: teammate's liveness is coapkb's own business (its team view), not DDS's.
    lease_duration_s: float = 30.0
    #: A reliable writer's heartbeat period while it has unacknowledged data.
    #: Cyclone's 100 ms is shorter than one 1500-byte frame takes at 35 kbit/s
    #: (340 ms): every heartbeat draws an ACKNACK, the discovery endpoints of
    #: a dozen participants saturated the link, and no request got through in
    #: 60 s (measured); at 1 s the same run completes.  None: Cyclone's.
    heartbeat_interval_s: float | None = 1.0


def _ms(seconds: float) -> str:
    return f"{round(seconds * 1000)}ms"


def _common(address: str, settings: DomainSettings) -> str:
    transport = "udp6" if ":" in address else "udp"
    return (
        "<General>"
        f"<Transport>{transport}</Transport>"
        f"<Interfaces><NetworkInterface address={quoteattr(address)}/></Interfaces>"
        "<AllowMulticast>false</AllowMulticast>"
        f"<MaxMessageSize>{settings.max_message_size}B</MaxMessageSize>"
        f"<MaxRexmitMessageSize>{settings.max_message_size}B</MaxRexmitMessageSize>"
        "</General>"
    )


def _internal(settings: DomainSettings) -> str:
    if settings.heartbeat_interval_s is None:
        return ""
    return f"<Internal><HeartbeatInterval>{_ms(settings.heartbeat_interval_s)}</HeartbeatInterval></Internal>"


def _document(general: str, discovery: str, internal: str = "") -> str:
    return (f'<CycloneDDS><Domain Id="any">{general}<Discovery>{discovery}</Discovery>{internal}'
            "</Domain></CycloneDDS>")


def server_domain_xml(address: str, port: int, settings: DomainSettings = DomainSettings()) -> str:
    """A domain whose one participant takes discovery and data on ``address:port``."""
    if not 0 < port < 65536:
        raise ValueError(f"a DDS participant needs a fixed port, not {port}")
    ports = (
        f"<Ports><Base>{port}</Base><DomainGain>0</DomainGain><ParticipantGain>0</ParticipantGain>"
        "<MulticastMetaOffset>0</MulticastMetaOffset><MulticastDataOffset>0</MulticastDataOffset>"
        "<UnicastMetaOffset>0</UnicastMetaOffset><UnicastDataOffset>0</UnicastDataOffset></Ports>"
    )
    discovery = (
        f"<ExternalDomainId>{settings.domain_id}</ExternalDomainId>"
        "<ParticipantIndex>0</ParticipantIndex>"
        f"{ports}"
        '<Peers AddLocalhost="false"/>'
        f"<LeaseDuration>{_ms(settings.lease_duration_s)}</LeaseDuration>"
    )
    return _document(_common(address, settings), discovery, _internal(settings))


def client_domain_xml(address: str, peer: str, settings: DomainSettings = DomainSettings()) -> str:
    """A domain on an ephemeral port of ``address`` whose only peer is ``peer`` (``host:port``)."""
    discovery = (
        f"<ExternalDomainId>{settings.domain_id}</ExternalDomainId>"
        "<ParticipantIndex>none</ParticipantIndex>"
        f'<Peers AddLocalhost="false"><Peer Address={quoteattr(peer)} PruneDelay="inf"/></Peers>'
        f"<LeaseDuration>{_ms(settings.lease_duration_s)}</LeaseDuration>"
    )
    return _document(_common(address, settings), discovery, _internal(settings))


def local_address_towards(host: str, port: int) -> str:
    """The local address the kernel routes ``host`` from (no packet is sent):
    the interface a client's participant must use to reach that peer."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_DGRAM) as s:
        s.connect((host, port))
        return str(s.getsockname()[0])


_UNSAFE = re.compile(r"[^A-Za-z0-9]")


@dataclass(frozen=True)
class TopicNames:
    """The topics between one server and one client."""

    #: Requests to the server, keyed by client: one reader at the server.
    requests: str
    #: Replies to this client (TRANSIENT_LOCAL: a reply written before the
    #: client's reader was discovered still reaches it).
    replies: str
    #: This client's observations' notifications, keyed by observation (KEEP_LAST 1).
    notifications: str


def server_tag(host: str, port: int) -> str:
    """The server's part of its topic names: ``127_0_0_1_7400``."""
    return f"{_UNSAFE.sub('_', host)}_{port}"


def topic_names(host: str, port: int, client: int) -> TopicNames:
    """The topics of server ``host:port`` and client ``client`` (its 64-bit id)."""
    tag = server_tag(host, port)
    return TopicNames(f"coapkb_rq_{tag}", f"coapkb_rp_{tag}_{client:016x}", f"coapkb_nt_{tag}_{client:016x}")
