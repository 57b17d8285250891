"""Secure robot-to-robot messaging (issue 12): OSCORE keyed by EDHOC, and
who may do what.

* :mod:`.keys`: a team's key material (``coapkb keys``): EDHOC credentials
  (CCS with a P-256 key), private keys, the trust list.
* :mod:`.policy`: the authorisation policy per resource (pure).
* :mod:`.coap`: OSCORE + EDHOC on the CoAP transport (aiocoap), client and
  server side.
* :mod:`.settings`: the ``[security]`` section of a robot's configuration.

Only :mod:`.coap` imports aiocoap's OSCORE stack; the rest is light.
"""

from .keys import SecurityError, TeamIdentity, TeamMember, TeamTrust, generate_team, load_identity, load_trust
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
    "generate_team",
    "load_identity",
    "load_trust",
]
