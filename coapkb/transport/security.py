"""The seams security plugs into.

A transport authenticates and protects its messages through a client-side
and a server-side security object; :mod:`coapkb.security` implements them
(OSCORE keyed by EDHOC for CoAP, CurveZMQ for ZeroMQ, mTLS for Zenoh), each
transport says what it needs of them in its own ``security`` module.  What
all of them share is here:

* the server side tells who sent a request: the member its security layer
  authenticated reaches the service as :attr:`Request.peer`, as a claim
  below the request interface (as aiocoap's OSCORE reports its contexts'
  claims);
* the server side carries the team's :class:`AccessRules`, which
  :func:`coapkb.transport.serve` puts in front of the service, once for every
  transport, as a :class:`GuardedService`.  Each transport asks
  :meth:`Service.admit` before anything else.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from .base import ResourceInfo, Service
from .messages import Request, Response


class AccessRules(Protocol):
    """Who may do what on a server."""

    def refusal(self, sender: str | None, method: str, path: str) -> Response | None:
        """The answer refusing ``method`` on ``path`` to ``sender`` (an
        authenticated member's name, None if the request was not protected),
        or None if it is allowed."""
        ...


class ClientSecurity(Protocol):
    """A client's side of a transport's security: what :func:`open_client`
    hands the transport (each transport's ``security`` module says what else
    it needs)."""


class ServerSecurity(Protocol):
    """A server's side of a transport's security: it authenticates the
    sender of each request (each transport's ``security`` module says how) and
    carries the rules :func:`coapkb.transport.serve` holds every request to."""

    @property
    def rules(self) -> AccessRules: ...


class GuardedService(Service):
    """``service`` behind ``rules``: what every secured server serves."""

    def __init__(self, service: Service, rules: AccessRules) -> None:
        self._service = service
        self._rules = rules

    def resources(self) -> list[ResourceInfo]:
        return self._service.resources()

    async def handle(self, request: Request) -> Response:
        return await self._service.handle(request)

    def subscribe(self, path: str, on_change: Callable[[], None]) -> Callable[[], None]:
        return self._service.subscribe(path, on_change)

    def admit(self, sender: str | None, method: str, path: str) -> Response | None:
        return self._rules.refusal(sender, method, path)
