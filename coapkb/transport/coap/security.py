"""What the CoAP transport needs of its security (OSCORE keyed by EDHOC,
implemented in :mod:`coapkb.security.coap`)."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Protocol

import aiocoap
import aiocoap.interfaces
import aiocoap.resource

from ..base import Endpoint
from ..security import AccessRules

#: Carries one handshake message to a peer and returns its answer (the
#: client transport's, with its retries).
HandshakePost = Callable[[Endpoint, bytes], Awaitable[aiocoap.Message]]


class CoapClientSecurity(Protocol):
    """Protects a client's requests: a security context per peer, established
    on first contact over the client's own exchanges."""

    #: What a request over a context the peer no longer has fails with.
    context_lost: tuple[type[BaseException], ...]

    def install(self, ctx: aiocoap.Context) -> None:
        """Make ``ctx`` protect every request it holds a context for."""
        ...

    async def ensure(self, ctx: aiocoap.Context, peer: Endpoint, post: HandshakePost | None = None) -> None:
        """A context for ``peer`` in ``ctx`` (the handshake on first contact,
        its messages sent with ``post``)."""
        ...

    def context(self, ctx: aiocoap.Context, peer: Endpoint) -> object | None:
        """The context in use for ``peer`` (None before the handshake)."""
        ...

    def forget(self, ctx: aiocoap.Context, peer: Endpoint, stale: object | None = None) -> None:
        """Drop ``peer``'s context (only if still ``stale``, when given)."""
        ...


class CoapServerSecurity(Protocol):
    """Unprotects requests and protects answers around a server's site, and
    tells who sent each request."""

    #: aiocoap's server credentials (the security contexts and the server's own).
    credentials: object

    @property
    def rules(self) -> AccessRules: ...

    def wrap(self, site: aiocoap.resource.Site) -> aiocoap.interfaces.Resource:
        """``site`` behind the security layer."""
        ...

    def sender(self, request: aiocoap.Message) -> str | None:
        """The member the (unprotected) ``request`` came from, None if it was not protected."""
        ...

    def sweep(self) -> None:
        """Forget the state that has aged out (called every few seconds)."""
        ...
