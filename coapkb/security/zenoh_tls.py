"""TLS with mutual authentication (mTLS) for the Zenoh transport, from the
team's key material (:mod:`.tls`): the Zenoh counterpart of OSCORE on CoAP
and CurveZMQ on ZeroMQ, so a secured benchmark compares like with like.

A ``zenoh://`` endpoint becomes a ``tls/host:port`` link and a
``zenoh+quic://`` endpoint keeps its ``quic/`` link with the same TLS
configuration; ``zenoh+udp://`` cannot be secured.  Both sides present their
member certificate and accept only the team CA's; host names are not
checked, but the client checks that the member serving an endpoint is the
one its configuration puts there.  Authorisation per resource
(:class:`~.policy.AccessPolicy`) holds in two layers: Zenoh's own access
control, keyed by the certificate's common name
(:data:`~.policy.ROLE_RULES`), and the team's policy per request, applied to
the member whose certificate authenticated the session the query names in
its ``source_info``.

docs/security.md ("Zenoh: mTLS") specifies both layers, what each binds a
request to, and why; docs/zenoh.md the links and what TLS costs.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import zenoh

from ..transport.base import Endpoint, PeerUnreachable
from ..transport.zenoh.mapping import key_for_path
from .errors import SecurityError
from .keys import TeamIdentity
from .policy import ROLE_RULES, AccessPolicy, TeamRules
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
    """``tcp/h:p`` -> ``tls/h:p``; ``quic/h:p`` is TLS already; anything else
    (``udp/h:p?rel=1``, Zenoh's reliable UDP) has no TLS in Zenoh."""
    protocol, sep, address = locator.partition("/")
    if sep and protocol == "tcp":
        return f"tls/{address}"
    if sep and protocol == "quic":
        return locator
    raise SecurityError(f"{locator}: zenoh+udp:// is Zenoh's reliable UDP, QUIC without encryption or "
                        f"authentication, and cannot be secured; use zenoh+quic:// (QUIC with the team's TLS) "
                        f"or zenoh:// (TLS over TCP)")


@dataclass
class ZenohServerSecurity:
    identity: TeamIdentity
    policy: AccessPolicy = field(default_factory=AccessPolicy)

    def __post_init__(self) -> None:
        self.files = self.identity.tls()  # one clear line now if a file is missing
        self.rules = TeamRules(self.identity.trust, self.policy,
                               unauthenticated="a Zenoh session over mTLS with a team certificate required")

    @staticmethod
    def locator(plain: str) -> str:
        return tls_locator(plain)

    def configure(self, config: zenoh.Config) -> None:
        """Make a (listening) session's config present our certificate and demand the client's."""
        _common(config, self.files)
        _insert(config, "listen_private_key", str(self.files.key))
        _insert(config, "listen_certificate", str(self.files.cert))
        config.insert_json5("access_control", json.dumps(self.access_control()))

    def access_control(self) -> dict[str, object]:
        """Zenoh's ``access_control``: ``/tasks`` only for the feeder's
        certificate, ``/decisions`` only for robots' (module doc, layer 1),
        and no member's session may publish, serve or answer through this one."""
        members = self.identity.trust.members
        rules: list[dict[str, object]] = []
        subjects: list[dict[str, object]] = []
        policies: list[dict[str, object]] = []
        # By key expression: Zenoh's access control cannot tell a rule's method from another.
        for index, rule in enumerate(ROLE_RULES):
            if not rule.by_key:
                continue
            others = [m.name for m in members if m.role not in rule.roles]
            if not others:
                continue
            rules.append({"id": f"r{index}", "messages": ["query"], "flows": ["ingress"], "permission": "deny",
                          "key_exprs": [key_for_path(rule.path)]})
            subjects.append({"id": f"s{index}", "cert_common_names": others})
            policies.append({"rules": [f"r{index}"], "subjects": [f"s{index}"]})
        # A client session only asks (and subscribes to its notifications). A
        # peer routes for its clients, so without this a member's session could
        # declare a queryable and answer, first, the queries others send to this
        # robot, or publish forged notifications on an observer's key.
        rules.append({"id": "ask-only", "messages": ["put", "delete", "declare_queryable", "reply"],
                      "flows": ["ingress"], "permission": "deny", "key_exprs": ["**"]})
        subjects.append({"id": "members", "cert_common_names": [m.name for m in members]})
        policies.append({"rules": ["ask-only"], "subjects": ["members"]})
        return {"enabled": True, "default_permission": "allow", "rules": rules, "subjects": subjects,
                "policies": policies}

    def sender(self, session: zenoh.Session, source_zid: str | None) -> str | None:
        """The member whose certificate authenticated the links of session ``source_zid``."""
        if not source_zid:
            return None
        names = {link.auth_identifier for link in session.info.links() if str(link.zid) == source_zid}
        if len(names) != 1:  # no such session, or links with different certificates
            return None
        name = names.pop()
        member = None if not name else self.identity.trust.by_name(name)
        return None if member is None else member.name


@dataclass
class ZenohClientSecurity:
    identity: TeamIdentity
    #: Which member serves at an endpoint (``host:port`` -> name); an endpoint
    #: not named here may be served by any member.
    expected: dict[str, str] | None = None

    def __post_init__(self) -> None:
        self.files = self.identity.tls()

    @staticmethod
    def locator(plain: str) -> str:
        return tls_locator(plain)

    def configure(self, config: zenoh.Config) -> None:
        """Make a (connecting) session's config present our certificate and check the server's."""
        _common(config, self.files)
        _insert(config, "connect_private_key", str(self.files.key))
        _insert(config, "connect_certificate", str(self.files.cert))

    def check_peer(self, session: zenoh.Session, peer: Endpoint) -> None:
        """Raise :class:`PeerUnreachable` unless the member expected at ``peer``
        is the one whose certificate the session's link authenticated."""
        name = (self.expected or {}).get(peer.hostport)
        if name is None:
            return
        names = {link.auth_identifier for link in session.info.links()}
        if names != {name}:
            found = ", ".join(sorted(n or "no certificate" for n in names)) or "no link"
            raise PeerUnreachable(f"{peer} presented {found}'s certificate, not {name}'s")
