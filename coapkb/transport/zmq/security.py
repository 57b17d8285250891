"""What the ZeroMQ transport needs of its security (CurveZMQ, implemented
in :mod:`coapkb.security.curve`)."""

from __future__ import annotations

from typing import Protocol

import zmq.asyncio

from ..base import Endpoint
from ..security import AccessRules


class ZmqClientSecurity(Protocol):
    def configure(self, sock: zmq.asyncio.Socket, peer: Endpoint) -> None:
        """Make ``sock`` (not yet connected) authenticate itself and ``peer``."""
        ...


class ZmqServerSecurity(Protocol):
    @property
    def rules(self) -> AccessRules: ...

    def configure(self, sock: zmq.asyncio.Socket, context: zmq.asyncio.Context) -> None:
        """Make ``sock`` (not yet bound) authenticate its clients, naming each
        in its messages' ``User-Id`` property."""
        ...

    def sender(self, user_id: str | None) -> str | None:
        """The member a message with ``User-Id`` ``user_id`` came from, or None."""
        ...

    def stop(self) -> None:
        """Stop what :meth:`configure` started."""
        ...
