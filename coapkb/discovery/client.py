"""A robot's side of discovery: register in the team's Resource Directory,
find the cluster's robots and their KB modules there, renew while running.

What the directory says is only where to look: the robot still checks
every teammate's identity on first contact (OSCORE keyed by EDHOC: the
responder at a discovered endpoint must hold the credential of the robot
registered there), and the directory accepts a registration only from the
robot it names (:class:`~coapkb.discovery.directory.DirectoryPolicy`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from dataclasses import replace

from aiocoap.util.linkformat import Link, LinkFormat, parse
from aiocoap.util.vendored.link_header import ParseException

from ..config import KB_MODULES, RobotConfig, Teammate
from ..errors import CoapkbError
from ..security import load_identity
from ..security.keys import TeamTrust
from ..transport import open_client, reliability_for
from ..transport.base import ClientTransport, Endpoint, TransportError
from ..transport.messages import ContentFormat, Method, Request
from ..transport.registry import parse_endpoint
from .directory import EP_LOOKUP_PATH, REGISTER_PATH, RES_LOOKUP_PATH
from .multicast import find_directory

log = logging.getLogger(__name__)

#: The resource type of a robot's KB resource; its ``kb`` attribute names one module.
KB_RT = "coapkb.kb"


class DiscoveryError(CoapkbError):
    """The directory refused this robot, or the team it shows cannot work."""


def registration_links(config: RobotConfig) -> str:
    """What a robot registers: its KB modules (one link each, ``rt=coapkb.kb;
    kb=MODULE``) and the state resources teammates observe."""
    me = config.team[config.robot_id]
    links = [Link("/kb", [("rt", KB_RT), ("kb", kb)]) for kb in me.kbs]
    links += [
        Link("/robot/plan", [("rt", "coapkb.plan"), ("obs", None)]),
        Link("/robot/state", [("rt", "coapkb.state"), ("obs", None)]),
        Link("/robot/outcome", [("rt", "coapkb.outcome"), ("obs", None)]),
    ]
    return str(LinkFormat(links))


class DirectoryClient:
    """One robot's registration in the directory, on a client of its own
    (its only peer is the directory, whose identity it expects)."""

    def __init__(self, config: RobotConfig, client: ClientTransport, trust: TeamTrust | None = None) -> None:
        discovery = config.discovery
        if discovery.rd is None:
            raise ValueError("no directory configured")
        self.rd: Endpoint = discovery.rd
        self._config = config
        self._client = client
        #: The team's trust list, when secured: only its robots are taken.
        self._trust = trust
        self._timeout = min(config.query_timeout_s, discovery.wait_s)
        self._registration = Request(
            Method.POST,
            REGISTER_PATH,
            {"ep": config.robot_id, "d": discovery.cluster, "lt": str(discovery.lifetime_s), "base": str(config.bind)},
            payload=registration_links(config).encode(),
            content_format=ContentFormat.LINK_FORMAT,
        )
        self._renewer: asyncio.Task[None] | None = None
        self.registered = False

    @classmethod
    async def open(cls, config: RobotConfig) -> DirectoryClient:
        security, trust = None, None
        if config.security is not None:
            from ..security.coap import ClientSecurity

            identity = load_identity(config.security.credentials, config.security.identity or config.robot_id)
            assert config.discovery.rd is not None
            security = ClientSecurity(identity, {config.discovery.rd.hostport: config.discovery.rd_identity})
            trust = identity.trust
        reliability = reliability_for("coap", link_kbps=config.link_kbps)
        client = await open_client("coap", reliability=reliability, security=security)
        return cls(config, client, trust)

    async def aclose(self) -> None:
        if self._renewer is not None:
            self._renewer.cancel()
            await asyncio.gather(self._renewer, return_exceptions=True)
        await self._client.aclose()

    async def register(self) -> None:
        """Register (or renew: the same registration again)."""
        response = await self._client.request(self.rd, self._registration, timeout=self._timeout)
        if not response.status.is_success:
            raise DiscoveryError(
                f"the directory at {self.rd} refused {self._config.robot_id}: {response.status.dotted} {response.text()}"
            )
        self.registered = True

    async def cluster(self) -> dict[str, Endpoint]:
        """The robots registered in this robot's cluster: watched (Observe on
        the endpoint lookup) until all ``members`` are there, or ``wait_s``
        has passed (then those registered so far)."""
        discovery = self._config.discovery
        request = Request(Method.GET, EP_LOOKUP_PATH, {"d": discovery.cluster}, accept=ContentFormat.LINK_FORMAT)
        found: dict[str, Endpoint] = {}
        try:
            async with asyncio.timeout(discovery.wait_s):
                async with contextlib.aclosing(self._client.observe(self.rd, request)) as answers:  # type: ignore[type-var]  # observe() is an async generator (it has aclose), typed an AsyncIterator
                    async for response in answers:
                        if not response.status.is_success:
                            raise DiscoveryError(f"endpoint lookup at {self.rd}: {response.status.dotted} {response.text()}")
                        found = self._endpoints(response.text())
                        if len(found) >= discovery.members:
                            break
        except TimeoutError:
            log.warning("after %gs, %d of %d robots of %s registered: %s", discovery.wait_s, len(found),
                        discovery.members, discovery.cluster, ", ".join(sorted(found)) or "none")
        return found

    def _links(self, text: str, what: str) -> list[Link]:
        """The links of a lookup's answer; a :class:`DiscoveryError` if it is
        not link-format (aiocoap's parser raises its own exception)."""
        try:
            links: list[Link] = parse(text).links
            return links
        except ParseException as exc:
            near = exc.args[1] if len(exc.args) > 1 else ""
            raise DiscoveryError(f"{what} at {self.rd}: the answer is not link-format (near {near[:80]})") from None

    def _endpoints(self, text: str) -> dict[str, Endpoint]:
        found: dict[str, Endpoint] = {}
        for link in self._links(text, "endpoint lookup"):
            attrs = dict(link.attr_pairs)
            ep, base = attrs.get("ep"), attrs.get("base")
            if not ep or not base:
                continue
            member = None if self._trust is None else self._trust.by_name(ep)
            if self._trust is not None and (member is None or member.role != "robot"):
                log.warning("directory lists %s, not a robot of the team: ignored", ep)
                continue
            try:
                endpoint = parse_endpoint(base)
            except ValueError:
                log.warning("directory lists %s at %r: not an endpoint", ep, base)
                continue
            if endpoint.scheme == self._config.transport:
                found[ep] = endpoint
        return found

    async def modules(self) -> dict[str, tuple[str, ...]]:
        """KB modules by the endpoint (``host:port``) that serves them (resource lookup)."""
        request = Request(
            Method.GET, RES_LOOKUP_PATH, {"rt": KB_RT, "d": self._config.discovery.cluster},
            accept=ContentFormat.LINK_FORMAT,
        )
        response = await self._client.request(self.rd, request, timeout=self._timeout)
        if not response.status.is_success:
            raise DiscoveryError(f"resource lookup at {self.rd}: {response.status.dotted} {response.text()}")
        held: dict[str, list[str]] = {}
        for link in self._links(response.text(), "resource lookup"):
            kb = dict(link.attr_pairs).get("kb")
            try:
                hostport = parse_endpoint(link.href).hostport
            except ValueError:
                continue
            if kb in KB_MODULES and kb not in held.setdefault(hostport, []):
                held[hostport].append(kb)
        return {hostport: tuple(kbs) for hostport, kbs in held.items()}

    async def find_team(self) -> dict[str, Teammate]:
        """Register, then the cluster's robots with their modules; {} if the
        directory does not answer (the caller falls back to its team table;
        the renewals keep trying to register)."""
        try:
            await self.register()
            endpoints = await self.cluster()
            modules = await self.modules()
        except TransportError as exc:
            log.warning("the directory at %s does not answer (%s): using the team table", self.rd, exc)
            return {}
        return {r: Teammate(r, e, modules.get(e.hostport, ())) for r, e in sorted(endpoints.items())}

    def start_renewing(self) -> None:
        self._renewer = asyncio.create_task(self._renew(), name="rd-renew")

    async def _renew(self) -> None:
        lifetime = self._config.discovery.lifetime_s
        while True:
            # A schedule, not a wait for an event: the registration must be
            # renewed before its lifetime runs out (at half of it, so one
            # lost renewal still leaves time for another).
            await asyncio.sleep(lifetime / 2 if self.registered else min(lifetime / 4, 5.0))
            try:
                await self.register()
            except (TransportError, DiscoveryError) as exc:
                self.registered = False
                log.warning("renewing the registration at %s: %s", self.rd, exc)


def _check_holders(config: RobotConfig) -> None:
    """Every KB module has a holder in the team found (or a central server is set)."""
    if config.central is None:
        missing = [kb for kb in KB_MODULES if config.holder_of(kb) is None]
        if missing:
            shown = ", ".join(f"{m.robot_id} ({'+'.join(m.kbs) or '-'})" for m in config.team.values())
            raise DiscoveryError(f"nobody in {config.discovery.cluster} holds {', '.join(missing)}: {shown}")


async def discover(config: RobotConfig) -> tuple[RobotConfig, DirectoryClient | None]:
    """``config`` with the teammates the directory shows (over the ``team``
    table's entries of the same names; the table's others stay, as the
    fallback), and the registration, renewing from now on.  Without a
    configured directory it is looked for by multicast first; if none
    answers, the team table is all there is (and no registration)."""
    if config.discovery.rd is None:
        rd = await find_directory(
            config.bind.host, port=config.discovery.multicast_port, timeout=min(config.discovery.wait_s, 3.0)
        )
        if rd is None:
            log.warning("no Resource Directory answered multicast discovery: using the team table")
            _check_holders(config)
            return config, None
        log.info("found the Resource Directory at %s by multicast", rd)
        config = replace(config, discovery=replace(config.discovery, rd=rd))
    directory = await DirectoryClient.open(config)
    try:
        found = await directory.find_team()
        me = config.team[config.robot_id]
        team = {**config.team, **found, config.robot_id: me}
        discovered = replace(config, team=team)
        _check_holders(discovered)
        log.info("discovered %s: %s", config.discovery.cluster,
                    ", ".join(f"{m.robot_id} {m.endpoint} {'+'.join(m.kbs)}" for m in team.values()))
        directory.start_renewing()
    except BaseException:
        await directory.aclose()
        raise
    return discovered, directory
