"""CurveZMQ (ZeroMQ RFC 26/CURVE, RFC 27/ZAP) with the team's keys, for the
ZeroMQ transport: the same trust list and policy as OSCORE on CoAP, so the
CoAP-vs-ZeroMQ comparison stays fair.

* The server's ROUTER is a CURVE server with its member's Curve key; a ZAP
  handler (pyzmq's asyncio authenticator) admits a connection only if the
  client's public key is in the trust list, and names the member as the
  connection's User-Id, which the transport reports as the request's sender
  (no connection, or a key not in the list, never gets that far: the
  handshake fails and the client's request times out).
* A client's DEALER to a peer is a CURVE client with its own key and the
  peer's public key (the member its configuration puts at that endpoint).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import zmq
import zmq.asyncio
from zmq.auth.asyncio import AsyncioAuthenticator

from ..transport.base import Endpoint
from .errors import SecurityError
from .keys import TeamIdentity
from .policy import AccessPolicy, TeamRules

ZAP_DOMAIN = "coapkb"


def _curve_keys(identity: TeamIdentity) -> tuple[bytes, bytes]:
    if identity.curve_secret is None or identity.member.curve_public is None:
        raise SecurityError(f"{identity.team_dir}: the team has no CurveZMQ keys (make it again with coapkb keys)")
    return identity.member.curve_public.encode("ascii"), identity.curve_secret.encode("ascii")


class _TeamAuthenticator(AsyncioAuthenticator):
    def __init__(self, context: zmq.asyncio.Context, security: ZmqServerSecurity) -> None:
        super().__init__(context)
        self._security = security

    def curve_user_id(self, client_public_key: bytes) -> str:
        member = self._security.identity.trust.by_curve(zmq.utils.z85.encode(client_public_key).decode("ascii"))
        return "" if member is None else member.name


@dataclass
class ZmqServerSecurity:
    identity: TeamIdentity
    policy: AccessPolicy = field(default_factory=AccessPolicy)

    def __post_init__(self) -> None:
        self._public, self._secret = _curve_keys(self.identity)
        self._auth: _TeamAuthenticator | None = None
        self.rules = TeamRules(self.identity.trust, self.policy)

    def callback(self, domain: str, key: bytes) -> bool:
        """ZAP: admit a client whose Curve public key (Z85) is a member's."""
        return self.identity.trust.by_curve(key.decode("ascii")) is not None

    def configure(self, sock: zmq.asyncio.Socket, context: zmq.asyncio.Context) -> None:
        """Make ``sock`` (not yet bound) a CURVE server with a ZAP handler on ``context``."""
        if self._auth is None:
            self._auth = _TeamAuthenticator(context, self)
            self._auth.start()
            self._auth.configure_curve_callback(domain=ZAP_DOMAIN, credentials_provider=self)
        sock.curve_secretkey = self._secret
        sock.curve_publickey = self._public
        sock.curve_server = True
        sock.zap_domain = ZAP_DOMAIN.encode("ascii")

    def sender(self, user_id: str | None) -> str | None:
        member = None if not user_id else self.identity.trust.by_name(user_id)
        return None if member is None else member.name

    def stop(self) -> None:
        if self._auth is not None:
            self._auth.stop()
            self._auth = None


@dataclass
class ZmqClientSecurity:
    identity: TeamIdentity
    #: Which member serves at an endpoint (``host:port`` -> name).
    expected: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._public, self._secret = _curve_keys(self.identity)

    def configure(self, sock: zmq.asyncio.Socket, peer: Endpoint) -> None:
        """Make ``sock`` (not yet connected) a CURVE client of ``peer``."""
        name = self.expected.get(peer.hostport)
        if name is None:
            raise SecurityError(f"no team member is known to serve {peer} (CurveZMQ needs the server's key)")
        member = self.identity.trust.by_name(name)
        if member is None or member.curve_public is None:
            raise SecurityError(f"{name} has no Curve key in the team's trust list")
        sock.curve_secretkey = self._secret
        sock.curve_publickey = self._public
        sock.curve_serverkey = member.curve_public.encode("ascii")
