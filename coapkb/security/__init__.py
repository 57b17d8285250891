"""Secure robot-to-robot messaging: OSCORE keyed by EDHOC, and
who may do what.

* :mod:`.keys`: a team's key material (``coapkb keys``): EDHOC credentials
  (CCS with a P-256 key), private keys, the trust list.
* :mod:`.policy`: the team's one access table per resource (pure).
* :mod:`.mechanisms`: each transport's mechanism, built from an identity:
  :func:`client_security` and :func:`server_security`.
* :mod:`.coap`: OSCORE + EDHOC on the CoAP transport (aiocoap), client and
  server side; :mod:`.curve`: CurveZMQ on ZeroMQ; :mod:`.zenoh_tls`: mTLS
  on Zenoh.  Each implements its transport's seams
  (:mod:`coapkb.transport.security`).
* :mod:`.settings`: the ``[security]`` section of a robot's configuration.

Only :mod:`.coap` imports aiocoap's OSCORE stack (:mod:`.curve` pyzmq,
:mod:`.zenoh_tls` Zenoh), each when its mechanism is built; the rest is light.
"""

from .errors import SecurityError
from .keys import TeamIdentity, TeamMember, TeamTrust, generate_team, load_identity, load_trust
from .mechanisms import client_security, mechanism_for, server_security
from .policy import AccessPolicy, Verdict
from .settings import SecurityConfig

__all__ = [
    "AccessPolicy",
    "SecurityConfig",
    "SecurityError",
    "TeamIdentity",
    "TeamMember",
    "TeamTrust",
    "Verdict",
    "client_security",
    "generate_team",
    "load_identity",
    "load_trust",
    "mechanism_for",
    "server_security",
]
