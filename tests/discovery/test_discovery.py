"""Discovery through a Resource Directory (RFC 9176) on real sockets and
real robot processes: who may register, a team whose robots know only
themselves, the static map as fallback, and a dead robot's registration
expiring."""

from __future__ import annotations

import asyncio
import signal
from dataclasses import replace
from pathlib import Path

import pytest
from aiocoap.util.linkformat import parse
from support import ONTOLOGIES, free_udp_port

from coapkb.config import ConfigError, DiscoveryConfig, RobotConfig, Teammate, dump_config, load_config, parse_config
from coapkb.discovery import DiscoveryError, ResourceDirectory, discover
from coapkb.discovery.client import DirectoryClient, registration_links
from coapkb.discovery.directory import EP_LOOKUP_PATH, REGISTER_PATH, RES_LOOKUP_PATH, DirectoryService
from coapkb.harness.team import Team, TeamSpec, draw_tasks
from coapkb.security import generate_team, load_identity
from coapkb.security.coap import ClientSecurity
from coapkb.security.keys import default_members
from coapkb.transport import Endpoint, open_client
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status

#: A discovery wait no test reaches: a test that gets there has waited for nothing.
WAIT_FOREVER_S = 600.0
#: How long a test waits for discovery to end (or a registration to expire): generous for a loaded machine.
COMPLETE_WITHIN_S = 60.0


@pytest.fixture
def team_dir(tmp_path: Path) -> Path:
    generate_team(tmp_path / "team", default_members(3))
    return tmp_path / "team"


def registration(ep: str, port: int, cluster: str = "cluster1", lt: int = 60) -> Request:
    return Request(
        Method.POST, REGISTER_PATH,
        {"ep": ep, "d": cluster, "lt": str(lt), "base": f"coap://127.0.0.1:{port}"},
        payload=b'</kb>;rt="coapkb.kb";kb="Object"', content_format=ContentFormat.LINK_FORMAT,
    )


async def test_only_a_robot_registers_and_only_itself(team_dir: Path) -> None:
    rd = await ResourceDirectory.start(Endpoint("coap", "127.0.0.1", 0), load_identity(team_dir, "feeder"))
    clients = {}
    try:
        for name in ("Robot1", "feeder"):
            security = ClientSecurity(load_identity(team_dir, name), {rd.endpoint.hostport: "feeder"})
            clients[name] = await open_client("coap", security=security)
        clients["nobody"] = await open_client("coap")
        robot1, feeder, nobody = clients["Robot1"], clients["feeder"], clients["nobody"]

        answer = await robot1.request(rd.endpoint, registration("Robot1", 5701), timeout=10)
        assert answer.status == Status.CREATED, answer
        # Another robot's name, a member that is no robot, no OSCORE at all.
        answer = await robot1.request(rd.endpoint, registration("Robot2", 5702), timeout=10)
        assert answer.status == Status.FORBIDDEN and "may not register as Robot2" in answer.text()
        answer = await feeder.request(rd.endpoint, registration("feeder", 5709), timeout=10)
        assert answer.status == Status.FORBIDDEN and "only robots register" in answer.text()
        answer = await nobody.request(rd.endpoint, registration("Robot3", 5703), timeout=10)
        assert answer.status == Status.UNAUTHORIZED
        assert rd.service.endpoints() == ["Robot1"]

        # Lookups are reads: any member; the unprotected get nothing.
        lookup = Request(Method.GET, EP_LOOKUP_PATH, {"d": "cluster1"}, accept=ContentFormat.LINK_FORMAT)
        answer = await feeder.request(rd.endpoint, lookup, timeout=10)
        [link] = parse(answer.text()).links
        assert dict(link.attr_pairs)["ep"] == "Robot1"
        assert dict(link.attr_pairs)["base"] == "coap://127.0.0.1:5701"
        assert (await nobody.request(rd.endpoint, lookup, timeout=10)).status == Status.UNAUTHORIZED
        lookup = Request(Method.GET, RES_LOOKUP_PATH, {"rt": "coapkb.kb", "kb": "Object"},
                         accept=ContentFormat.LINK_FORMAT)
        [link] = parse((await robot1.request(rd.endpoint, lookup, timeout=10)).text()).links
        assert link.href == "coap://127.0.0.1:5701/kb"
        # The directory is discoverable as RFC 9176 says (open, like every /.well-known/core).
        wkc = Request(Method.GET, "/.well-known/core", {"rt": "core.rd*"})
        assert "</rd>" in (await nobody.request(rd.endpoint, wkc, timeout=10)).text()
    finally:
        for client in clients.values():
            await client.aclose()
        await rd.aclose()


def _robot_config(
    robot_id: str, port: int, kbs: tuple[str, ...], rd: Endpoint | None, **discovery: object
) -> RobotConfig:
    return RobotConfig(
        robot_id=robot_id, bind=Endpoint("coap", "127.0.0.1", port), kb_files=(),
        team={robot_id: Teammate(robot_id, Endpoint("coap", "127.0.0.1", port), kbs)},
        discovery=DiscoveryConfig("rd", rd=rd, cluster="c1", members=3, **discovery),  # type: ignore[arg-type]
    )


async def test_robots_knowing_only_themselves_find_each_other_and_the_modules() -> None:
    rd = await ResourceDirectory.start(Endpoint("coap", "127.0.0.1", 0))
    holdings = {"Robot1": ("Location", "Object"), "Robot2": ("Object", "Capability"), "Robot3": ("Capability", "Location")}
    # A wait far longer than the test's timeout: discovery ends when the cluster is complete.
    configs = [_robot_config(r, 5800 + i, kbs, rd.endpoint, wait_s=WAIT_FOREVER_S)
               for i, (r, kbs) in enumerate(holdings.items())]
    try:
        async with asyncio.timeout(COMPLETE_WITHIN_S):
            found = await asyncio.gather(*(discover(c) for c in configs))
        for config, _directory in found:
            assert {r: m.kbs for r, m in config.team.items()} == holdings
            assert config.team["Robot2"].endpoint == Endpoint("coap", "127.0.0.1", 5801)
        # A fourth robot of another cluster sees nobody of c1 and cannot work alone.
        lone = _robot_config("Robot4", 5803, ("Location",), rd.endpoint, wait_s=0.5)
        with pytest.raises(DiscoveryError, match="nobody in c2 holds Object, Capability"):
            await discover(replace(lone, discovery=replace(lone.discovery, cluster="c2")))
    finally:
        for _, directory in found:
            await directory.aclose()
        await rd.aclose()


async def test_an_unreachable_directory_leaves_the_team_table() -> None:
    nowhere = Endpoint("coap", "127.0.0.1", free_udp_port())
    config = _robot_config("Robot1", 5901, ("Location",), nowhere, wait_s=2.0)
    static = {
        **config.team,
        "Robot2": Teammate("Robot2", Endpoint("coap", "127.0.0.1", 5902), ("Object",)),
        "Robot3": Teammate("Robot3", Endpoint("coap", "127.0.0.1", 5903), ("Capability",)),
    }
    config = replace(config, team=static, query_timeout_s=2.0)
    discovered, directory = await discover(config)
    try:
        assert discovered.team == static and not directory.registered
    finally:
        await directory.aclose()


def test_discovery_section_is_checked(tmp_path: Path) -> None:
    base = {
        "robot_id": "Robot1", "bind": "coap://127.0.0.1:5701",
        "team": {"Robot1": {"endpoint": "coap://127.0.0.1:5701", "kbs": ["Location"]}},
    }
    # With a directory the team table may list this robot alone.
    config = parse_config({**base, "discovery": {"method": "rd", "rd": "coap://127.0.0.1:5690", "cluster": "c1"}})
    assert config.discovery == DiscoveryConfig("rd", rd=Endpoint("coap", "127.0.0.1", 5690), cluster="c1")
    path = tmp_path / "r1.toml"
    path.write_text(dump_config(config))
    assert load_config(path) == config
    with pytest.raises(ConfigError, match="team: nobody holds"):
        parse_config(base)
    for bad, match in (
        ({"method": "dns"}, "discovery.method: 'dns' is not one of static, rd"),
        ({"method": "rd", "multicast_port": 0}, "discovery.multicast_port: must be a UDP port"),
        ({"method": "rd", "rd": "zmq://127.0.0.1:5690"}, "discovery.rd: a Resource Directory is a coap://"),
        ({"method": "rd", "rd": "coap://h:1", "lifetime_s": 0}, "discovery.lifetime_s: must be at least 1"),
        ({"method": "rd", "rd": "coap://h:1", "cluster": "a b"}, "discovery.cluster"),
        ({"method": "rd", "rd": "coap://h:1", "ttl": 3}, "discovery.ttl: unknown field"),
    ):
        with pytest.raises(ConfigError, match=match):
            parse_config({**base, "discovery": bad})
    zmq = {**base, "bind": "zmq://127.0.0.1:5701", "team": {"Robot1": {"endpoint": "zmq://127.0.0.1:5701"}}}
    with pytest.raises(ConfigError, match="a Resource Directory speaks CoAP"):
        parse_config({**zmq, "discovery": {"method": "rd", "rd": "coap://127.0.0.1:5690"}})


async def test_robots_find_the_directory_by_multicast() -> None:
    # On loopback multicast works (IP_MULTICAST_IF 127.0.0.1): robots that
    # know neither teammates nor the directory's address find both.  A
    # port of its own, so parallel runs on this host do not answer.
    port = free_udp_port()
    rd = await ResourceDirectory.start(Endpoint("coap", "127.0.0.1", 0), multicast_port=port)
    holdings = {"Robot1": ("Location",), "Robot2": ("Object",), "Robot3": ("Capability",)}
    configs = [_robot_config(r, 5810 + i, kbs, None, multicast_port=port, wait_s=WAIT_FOREVER_S)
               for i, (r, kbs) in enumerate(holdings.items())]
    found = []
    try:
        async with asyncio.timeout(COMPLETE_WITHIN_S):
            found = await asyncio.gather(*(discover(c) for c in configs))
        for config, directory in found:
            assert directory is not None and directory.rd == rd.endpoint
            assert {r: m.kbs for r, m in config.team.items()} == holdings
    finally:
        for _, directory in found:
            if directory is not None:
                await directory.aclose()
        await rd.aclose()
    # Nobody answers: the team table, at once after the wait (and it must do).
    lone = _robot_config("Robot1", 5810, ("Location",), None, multicast_port=free_udp_port(), wait_s=0.6)
    with pytest.raises(DiscoveryError, match="nobody in c1 holds Object, Capability: Robot1 [(]Location[)]"):
        async with asyncio.timeout(COMPLETE_WITHIN_S):
            await discover(lone)
    full = replace(lone, team={**lone.team, "Robot2": Teammate(
        "Robot2", Endpoint("coap", "127.0.0.1", 5811), ("Object", "Capability"))})
    assert await discover(full) == (full, None)


def test_registration_names_the_modules() -> None:
    config = _robot_config("Robot1", 5701, ("Location", "Object"), Endpoint("coap", "127.0.0.1", 5690))
    links = {(link.href, dict(link.attr_pairs).get("kb")) for link in parse(registration_links(config)).links}
    assert ("/kb", "Location") in links and ("/kb", "Object") in links


class _Answers:
    """A client whose every answer is ``payload``, as a directory's would be."""

    def __init__(self, payload: bytes) -> None:
        self.payload = payload

    async def request(self, peer: Endpoint, request: Request, timeout: float | None = None) -> Response:
        return Response(Status.CONTENT, self.payload, ContentFormat.LINK_FORMAT)


#: Found by fuzzing: aiocoap's link-format parser raised its own
#: ParseException through the lookups, a traceback at a robot's start.
NOT_LINK_FORMAT = b'<coap://127.0.0.1:5721/kb>;rt=;kb="Object"'


async def test_links_without_a_value_cannot_break_the_lookups() -> None:
    # Found by fuzzing: a registration of </kb>;rt made aiocoap's resource
    # lookup raise on every later ?rt= filter (a 5.00 for the whole team),
    # and a wildcard on a flag attribute (obs) raised as well.
    service = DirectoryService(authenticated=False)
    try:
        bad = replace(registration("Robot2", 5702), payload=b'<coap://h:5>;rt;kb="Obj"')
        answer = await service.router.handle(bad)
        assert answer.status == Status.BAD_REQUEST and "rt needs a value" in answer.text(), answer
        config = _robot_config("Robot1", 5701, ("Object",), Endpoint("coap", "127.0.0.1", 5690))
        ours = replace(registration("Robot1", 5701), payload=registration_links(config).encode())
        assert (await service.router.handle(ours)).status == Status.CREATED
        found = await service.router.handle(Request(Method.GET, RES_LOOKUP_PATH, {"rt": "coapkb.kb"}))
        assert found.status == Status.CONTENT and b'kb="Object"' in found.payload, found
        wildcard = await service.router.handle(Request(Method.GET, RES_LOOKUP_PATH, {"obs": "x*"}))
        assert wildcard.status == Status.BAD_REQUEST, wildcard
    finally:
        service.close()


async def test_a_lookup_answer_that_is_not_link_format_is_a_discovery_error() -> None:
    config = _robot_config("Robot1", 5701, ("Location",), Endpoint("coap", "127.0.0.1", 5690))
    client = DirectoryClient(config, _Answers(NOT_LINK_FORMAT))  # type: ignore[arg-type]
    with pytest.raises(DiscoveryError, match="resource lookup at coap://127.0.0.1:5690: the answer is not link-format"):
        await client.modules()
    with pytest.raises(DiscoveryError, match="endpoint lookup .* not link-format"):
        client._endpoints(NOT_LINK_FORMAT.decode())

async def test_team_run_with_robots_that_know_only_themselves() -> None:
    # OSCORE on (the default): the directory takes only robots' own
    # registrations, and each robot checks every teammate it found by EDHOC.
    tasks = draw_tasks(8, ONTOLOGIES, seed=3)
    spec = TeamSpec(robots=6, discovery="rd", query_timeout_s=5.0, task_timeout_s=30.0)
    async with asyncio.timeout(60):
        async with Team.launch(spec) as team:
            for robot_id in spec.robot_ids:
                config = load_config(team.workdir / f"{robot_id}.toml")
                assert list(config.team) == [robot_id] and config.discovery.method == "rd"
            assert team.directory.service.endpoints() == spec.robot_ids
            record = await team.run(tasks)
    assert [t.object for t in record.tasks] == tasks
    assert all(t.agreed and t.fate in ("assigned", "skipped") for t in record.tasks), record.tasks
    assert sum(s.executed for s in record.robot_stats.values()) == sum(t.fate == "assigned" for t in record.tasks)


@pytest.mark.slow
async def test_a_dead_robots_registration_expires_and_the_others_renew() -> None:
    lifetime = 2
    spec = TeamSpec(robots=3, discovery="rd", rd_lifetime_s=lifetime, security=False)
    async with asyncio.timeout(60):
        async with Team.launch(spec) as team:
            service = team.directory.service
            changed = asyncio.Event()
            service.router.subscribe(EP_LOOKUP_PATH, changed.set)
            team.processes["Robot2"].send_signal(signal.SIGKILL)
            await team.processes["Robot2"].wait()
            async with asyncio.timeout(COMPLETE_WITHIN_S):  # expires after its lifetime (not never)
                while "Robot2" in service.endpoints():
                    changed.clear()
                    await changed.wait()
            # The live ones renew: still there after more than a lifetime.
            await asyncio.sleep(lifetime * 1.5)
            assert service.endpoints() == ["Robot1", "Robot3"]
