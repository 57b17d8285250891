"""A Resource Directory (RFC 9176) for a team: aiocoap's registry behind
coapkb's transport and security.

The registry, its lifetimes and its lookup filters are aiocoap's own
(:mod:`aiocoap.cli.rd`: ``CommonRD`` and the endpoint and resource lookup
interfaces); what is coapkb's is the wiring: the interfaces are resources of
a :class:`~coapkb.transport.router.Router`, so they are served by the same
CoAP server as everything else, behind OSCORE keyed by EDHOC and the team's
policy, and a registration is refused unless the team member that sent it
registers itself (``ep`` = its authenticated name).

=====================  ======  ===============================================
``/rd``                POST    register (``?ep=&d=&lt=&base=``, link-format
                               body); the same POST again renews
``/rd-lookup/ep``      GET     endpoint lookup, filters as RFC 9176 section 7;
                               observable
``/rd-lookup/res``     GET     resource lookup; observable
=====================  ======  ===============================================

Deviation from RFC 9176: the answer to a registration carries no
Location-Path (coapkb's messages have no such option), so a robot renews by
registering again, which the RFC allows (a registration with the same ``ep``
and ``d`` replaces the old one, section 5).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import aiocoap
import aiocoap.error
from aiocoap.cli.rd import CommonRD, EndpointLookupInterface, ResourceLookupInterface
from aiocoap.util.linkformat import parse

from ..security.keys import TeamMember
from ..security.policy import ALLOW, AccessPolicy, Verdict
from ..transport import serve
from ..transport.base import Endpoint, ResourceInfo, ServerTransport
from ..transport.messages import ContentFormat, Request, Response, Status
from ..transport.registry import parse_endpoint
from ..transport.router import Router

log = logging.getLogger(__name__)

REGISTER_PATH = "/rd"
EP_LOOKUP_PATH = "/rd-lookup/ep"
RES_LOOKUP_PATH = "/rd-lookup/res"
#: Longest lifetime accepted, seconds (RFC 9176's default, 25 h).
MAX_LIFETIME_S = 90_000


class _TeamRD(CommonRD):
    class Registration(CommonRD.Registration):
        # aiocoap keeps an expired registration 15 s longer; a team wants a
        # dead robot gone when its lifetime ends, not later.
        grace_period = 0


@dataclass(frozen=True)
class DirectoryPolicy(AccessPolicy):
    """The team's policy, plus: only robots register (lookups are reads, open
    to every member as any GET is)."""

    def decide(self, member: TeamMember | None, method: str, path: str) -> Verdict:
        if member is not None and method == "POST" and path == REGISTER_PATH:
            if member.role == "robot":
                return ALLOW
            return Verdict(False, Status.FORBIDDEN, "only robots register in the team's directory")
        return super().decide(member, method, path)


class DirectoryService:
    """The registration and lookup interfaces as a :class:`Router`.

    ``authenticated``: a registration must come from the robot it names
    (the server's security layer tells who sent it); without security
    anybody may register anything, as in any unprotected RD."""

    def __init__(self, *, authenticated: bool) -> None:
        self._authenticated = authenticated
        self.router = Router()
        self._rd = _TeamRD(log=log)
        # aiocoap's lookup resources, asked with an aiocoap message made from ours.
        self._lookups = {
            EP_LOOKUP_PATH: EndpointLookupInterface(common_rd=self._rd),
            RES_LOOKUP_PATH: ResourceLookupInterface(common_rd=self._rd),
        }
        self._rd.register_change_callback(self._changed)
        add = self.router.add
        add(ResourceInfo(REGISTER_PATH, rt="core.rd", ct=(40,), methods=("POST",)), self._register)
        add(ResourceInfo(EP_LOOKUP_PATH, rt="core.rd-lookup-ep", ct=(40,), obs=True), self._lookup)
        add(ResourceInfo(RES_LOOKUP_PATH, rt="core.rd-lookup-res", ct=(40,), obs=True), self._lookup)

    def endpoints(self) -> list[str]:
        """The names of the robots registered now."""
        return sorted(ep for ep, _ in self._rd._by_key)

    def close(self) -> None:
        for registration in list(self._rd.get_endpoints()):
            registration.timeout.cancel()

    def _changed(self) -> None:
        for path in self._lookups:
            self.router.notify(path)

    async def _register(self, request: Request) -> Response:
        if request.content_format not in (None, ContentFormat.LINK_FORMAT):
            return Response.error(Status.UNSUPPORTED_CONTENT_FORMAT, "register with a link-format body (40)")
        ep, base = request.query.get("ep"), request.query.get("base")
        if not ep or not base:
            return Response.error(Status.BAD_REQUEST, "ep and base are required")
        if self._authenticated and request.peer != ep:
            # Identities are the security layer's: a robot registers only itself.
            return Response.error(Status.FORBIDDEN, f"{request.peer} may not register as {ep}")
        try:
            links = parse(request.payload.decode("utf-8"))
            for link in links.links:
                # aiocoap's lookups split rt and if into words: a link with
                # none would fail every later lookup filtering on them.
                missing = [key for key, value in link.attr_pairs if value is None and key in ("rt", "if")]
                if missing:
                    raise ValueError(f"{link.href}: {missing[0]} needs a value")
            lifetime = int(request.query.get("lt", MAX_LIFETIME_S))
            if not 1 <= lifetime <= MAX_LIFETIME_S:
                raise ValueError(f"lt must be 1 to {MAX_LIFETIME_S}")
            parse_endpoint(base)
        except (UnicodeDecodeError, ValueError) as exc:
            return Response.error(Status.BAD_REQUEST, f"not a registration: {exc}")
        except Exception as exc:  # noqa: BLE001 - the link-format parser's own errors
            return Response.error(Status.BAD_REQUEST, f"not link-format: {exc}")
        known = self._rd._by_key.get((ep, request.query.get("d")))
        if known is not None and known.base == base and str(known.links) == str(links):
            # A renewal: the same registration again restarts its lifetime
            # and changes nothing a lookup shows, so no observer is notified.
            known.lt = lifetime
            known.refresh_timeout()
            return Response(Status.CHANGED)
        params = {k: [v] for k, v in request.query.items()}
        params["lt"] = [str(lifetime)]
        try:
            registration = self._rd.initialize_endpoint(None, params)
        except aiocoap.error.ConstructionRenderableError as exc:
            return Response.error(Status.BAD_REQUEST, str(exc.message))
        registration.links = links
        self._changed()  # again: the registry announced it before it had its links
        log.info("registered %s (d=%s, lt=%d s)", ep, request.query.get("d"), lifetime)
        return Response(Status.CREATED)

    async def _lookup(self, request: Request) -> Response:
        message = aiocoap.Message(
            code=aiocoap.GET,
            uri_query=[f"{k}={v}" if v else k for k, v in request.query.items()],
            accept=request.accept,
        )
        try:
            answer = await self._lookups[request.path].render_get(message)
        except aiocoap.error.ConstructionRenderableError as exc:
            return Response.error(Status.BAD_REQUEST, str(exc.message))
        except AttributeError:
            # aiocoap matches a wildcard with str methods, and a flag
            # attribute (obs) registered without a value has none.
            return Response.error(Status.BAD_REQUEST, "a wildcard cannot match an attribute without a value")
        if answer.code == aiocoap.NOT_ACCEPTABLE:
            return Response.error(Status.NOT_ACCEPTABLE, "lookups answer in link-format (40)")
        return Response(Status.CONTENT, answer.payload, ContentFormat.LINK_FORMAT)


class ResourceDirectory:
    """A :class:`DirectoryService` served over CoAP: the feeder of ``coapkb
    team`` hosts one; ``security`` is a
    :class:`~coapkb.security.coap.ServerSecurity` (whose policy is made a
    :class:`DirectoryPolicy`) or None."""

    def __init__(self, service: DirectoryService, server: ServerTransport, announcer: Any = None) -> None:
        self.service = service
        self.server = server
        #: Answers multicast discovery of this directory (or None).
        self.announcer = announcer

    @property
    def endpoint(self) -> Endpoint:
        return self.server.endpoint

    @classmethod
    async def start(
        cls, bind: Endpoint, identity: Any = None, multicast_port: int | None = None
    ) -> ResourceDirectory:
        """Serve on ``bind`` (port 0: any); ``identity``: the host's
        :class:`~coapkb.security.TeamIdentity` (OSCORE/EDHOC), or None;
        ``multicast_port``: also answer multicast discovery there, on
        ``bind``'s interface."""
        security = None
        if identity is not None:
            from ..security.coap import ServerSecurity

            security = ServerSecurity(identity, DirectoryPolicy())
        service = DirectoryService(authenticated=security is not None)
        server = await serve(service.router, bind, security=security)
        announcer = None
        if multicast_port is not None:
            from .multicast import MulticastAnnouncer

            try:
                announcer = await MulticastAnnouncer.start(server.endpoint, bind.host, multicast_port)
            except BaseException:
                await server.aclose()
                raise
        return cls(service, server, announcer)

    async def aclose(self) -> None:
        if self.announcer is not None:
            self.announcer.close()
        self.service.close()
        await self.server.aclose()
