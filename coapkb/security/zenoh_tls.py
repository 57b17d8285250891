"""TLS with mutual authentication (mTLS) for the Zenoh transport, from the
team's key material (:mod:`.tls`): the Zenoh counterpart of OSCORE on CoAP
and CurveZMQ on ZeroMQ, so a secured benchmark compares like with like.

* Only ``zenoh://`` endpoints, which become Zenoh ``tls/host:port`` links
  (TLS 1.3 over TCP, rustls).  ``zenoh+udp://`` has no security: Zenoh's UDP
  link has no TLS (a DTLS link does not exist in Zenoh 1.x), and QUIC would
  be a third link type to compare; a secured team refuses it.
* Both sides present their member certificate and accept only a peer whose
  certificate the team CA issued (``enable_mtls``), so a process without a
  team certificate, or with one from another CA, cannot open a session at
  all: the handshake fails and the client reports the peer unreachable.
* Host names are not checked (``verify_name_on_connect`` false): a
  certificate names a member, not a host, and robots are addressed by IP.
  Which member serves an endpoint is therefore not checked either (CurveZMQ
  and EDHOC do check it): any team member could answer at a teammate's
  address.

Authorisation per resource (:class:`~.policy.AccessPolicy`): Zenoh reports
a link's certificate common name (``Link.auth_identifier``), but not which
link a query came in on.  The client therefore sends its session id in the
query's ``source_info``, and the server takes the member to be the one whose
certificate authenticated the link from that session.  That binds a query to
a certificate as far as the querier tells the truth about its session id: an
outsider cannot get in at all (mTLS), a member's unmodified client is held to
its role, but a member that rewrote its Zenoh client could claim a connected
teammate's session id and so its role.  OSCORE binds each request to the
sender's key; on Zenoh the per-resource policy is this weaker, session-level
check, which docs/security.md states.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import zenoh

from ..transport.messages import Request
from .keys import SecurityError, TeamIdentity, TeamMember
from .policy import AccessPolicy, Verdict
from .tls import TlsFiles

_TLS = "transport/link/tls/"


def _insert(config: zenoh.Config, key: str, value: object) -> None:
    config.insert_json5(_TLS + key, json.dumps(value))


def _common(config: zenoh.Config, files: TlsFiles) -> None:
    # Paths, not the keys' contents: Zenoh reads the files itself.
    _insert(config, "root_ca_certificate", str(files.ca))
    _insert(config, "enable_mtls", True)
    _insert(config, "verify_name_on_connect", False)


def tls_locator(locator: str) -> str:
    """``tcp/h:p`` -> ``tls/h:p``; anything else has no TLS in Zenoh."""
    protocol, sep, address = locator.partition("/")
    if protocol != "tcp" or not sep:
        raise SecurityError(f"{locator}: Zenoh has TLS only over TCP (zenoh://); zenoh+udp:// cannot be secured")
    return f"tls/{address}"


@dataclass
class ZenohServerSecurity:
    identity: TeamIdentity
    policy: AccessPolicy = field(default_factory=AccessPolicy)

    def __post_init__(self) -> None:
        self.files = self.identity.tls()  # one clear line now if a file is missing

    def configure(self, config: zenoh.Config) -> None:
        """Make a (listening) session's config present our certificate and demand the client's."""
        _common(config, self.files)
        _insert(config, "listen_private_key", str(self.files.key))
        _insert(config, "listen_certificate", str(self.files.cert))

    def member_of(self, session: zenoh.Session, source_zid: str | None) -> TeamMember | None:
        """The member whose certificate authenticated the links of session ``source_zid``."""
        if not source_zid:
            return None
        names = {link.auth_identifier for link in session.info.links() if str(link.zid) == source_zid}
        if len(names) != 1:  # no such session, or links with different certificates
            return None
        name = names.pop()
        return None if not name else self.identity.trust.by_name(name)

    def check(self, member: TeamMember | None, request: Request) -> Verdict:
        verdict = self.policy.decide(member, str(request.method.value), request.path)
        if member is None and not verdict.allowed:
            return Verdict(False, verdict.status, "a Zenoh session over mTLS with a team certificate required")
        return verdict


@dataclass
class ZenohClientSecurity:
    identity: TeamIdentity

    def __post_init__(self) -> None:
        self.files = self.identity.tls()

    def configure(self, config: zenoh.Config) -> None:
        """Make a (connecting) session's config present our certificate and check the server's."""
        _common(config, self.files)
        _insert(config, "connect_private_key", str(self.files.key))
        _insert(config, "connect_certificate", str(self.files.cert))
