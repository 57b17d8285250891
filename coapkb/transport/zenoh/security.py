"""What the Zenoh transport needs of its security (mTLS with the team's
certificates, implemented in :mod:`coapkb.security.zenoh_tls`)."""

from __future__ import annotations

from typing import Protocol

import zenoh

from ..base import Endpoint
from ..security import AccessRules


class ZenohClientSecurity(Protocol):
    def locator(self, plain: str) -> str:
        """The link to use instead of ``plain`` (``tcp/h:p`` -> ``tls/h:p``,
        ``quic/h:p`` as it is); raises if it cannot be secured (``udp/``)."""
        ...

    def configure(self, config: zenoh.Config) -> None:
        """Make a (connecting) session's config authenticate itself and its peer
        (Zenoh's ``transport/link/tls/...`` keys, which TLS and QUIC links share)."""
        ...

    def check_peer(self, session: zenoh.Session, peer: Endpoint) -> None:
        """Raise :class:`~coapkb.transport.PeerUnreachable` unless the member
        expected at ``peer`` is the one the session authenticated."""
        ...


class ZenohServerSecurity(Protocol):
    @property
    def rules(self) -> AccessRules: ...

    def locator(self, plain: str) -> str:
        """The link to listen on instead of ``plain``; raises if it cannot be secured."""
        ...

    def configure(self, config: zenoh.Config) -> None:
        """Make a (listening) session's config authenticate its clients."""
        ...

    def sender(self, session: zenoh.Session, source_zid: str | None) -> str | None:
        """The member whose credential authenticated the querier's session ``source_zid``, or None."""
        ...
