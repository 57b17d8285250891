"""Zenoh over QUIC (``zenoh+quic://``) and Zenoh's reliable UDP
(``zenoh+udp://`` = ``udp/h:p?rel=1``, QUIC streams without TLS): real UDP
sockets on 127.0.0.1, client and server in this process.

QUIC runs with the team's certificates (mutual TLS, as ``zenoh://`` over
TLS) or, without them, with the anonymous listener certificate of
:mod:`coapkb.transport.zenoh.anonymous_tls`.  Garbage datagrams at the port
are the transport contract's (tests/transport/test_contract.py), as for
every datagram transport.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
from collections.abc import Callable
from pathlib import Path

import pytest
import zenoh
from support import ONTOLOGIES, ServerProcess, coapkb, free_udp_port

from coapkb.security import AccessPolicy, SecurityError, generate_team, load_identity
from coapkb.security.keys import default_members
from coapkb.security.mechanisms import client_security, server_security
from coapkb.transport import Endpoint, PeerUnreachable, TransportError, open_client, serve
from coapkb.transport.base import ResourceInfo, Service
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status
from coapkb.transport.zenoh.mapping import locator
from coapkb.transport.zenoh.transport import ZenohClientTransport, ZenohOptions, ZenohServerTransport

#: The two links this file is about; both listen on UDP.
LINKS = ("zenoh+quic", "zenoh+udp")


class Counter(Service):
    """``/counter`` (observable), ``/tasks`` and ``/decisions``; records what got through."""

    def __init__(self) -> None:
        self.value = 0
        self.calls: list[tuple[str, str, str | None]] = []
        self._subscribers: dict[int, Callable[[], None]] = {}
        self._next = 0
        self.unsubscribed = asyncio.Event()

    def resources(self) -> list[ResourceInfo]:
        return [ResourceInfo("/counter", obs=True), ResourceInfo("/tasks", methods=("GET", "POST")),
                ResourceInfo("/decisions", methods=("POST",))]

    async def handle(self, request: Request) -> Response:
        self.calls.append((str(request.method), request.path, request.peer))
        if request.path == "/counter":
            return Response(Status.CONTENT, str(self.value).encode(), ContentFormat.TEXT)
        if request.path in ("/tasks", "/decisions"):
            return Response(Status.CHANGED if request.method == Method.POST else Status.CONTENT, b"ok")
        return Response.error(Status.NOT_FOUND, f"no resource {request.path}")

    def subscribe(self, path: str, on_change: Callable[[], None]) -> Callable[[], None]:
        if path != "/counter":
            return lambda: None
        key = self._next = self._next + 1
        self._subscribers[key] = on_change

        def cancel() -> None:
            self._subscribers.pop(key, None)
            self.unsubscribed.set()

        return cancel

    def bump(self) -> None:
        self.value += 1
        for on_change in list(self._subscribers.values()):
            on_change()


@pytest.fixture(scope="module")
def team(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``coapkb keys``'s files for three robots, the feeder, central and operator."""
    team_dir = tmp_path_factory.mktemp("quic") / "team"
    generate_team(team_dir, default_members(3))
    return team_dir


async def _observe_three(client, peer: Endpoint, service: Counter) -> list[bytes]:
    """The first answer and two notifications, then deregistration."""
    values: list[bytes] = []
    async with contextlib.aclosing(client.observe(peer, Request(Method.GET, "/counter"), timeout=5)) as updates:
        async for response in updates:
            values.append(response.payload)
            if len(values) == 3:
                break
            service.bump()
    await asyncio.wait_for(service.unsubscribed.wait(), 5)
    return values


# =========================================================================== without the team's keys


@pytest.mark.parametrize("scheme", LINKS)
async def test_request_and_observe_without_credentials(scheme: str) -> None:
    service = Counter()
    async with await ZenohServerTransport.start(service, Endpoint(scheme, "127.0.0.1", 0)) as server:
        assert server.endpoint.scheme == scheme and server.endpoint.port != 0
        async with ZenohClientTransport() as client:
            answer = await client.request(server.endpoint, Request(Method.GET, "/counter"), timeout=5)
            assert (answer.status, answer.payload) == (Status.CONTENT, b"0")
            missing = await client.request(server.endpoint, Request(Method.GET, "/nope"), timeout=5)
            assert missing.status == Status.NOT_FOUND
            assert await _observe_three(client, server.endpoint, service) == [b"0", b"1", b"2"]
            assert server.observation_count == 0
            (link,) = client._sessions[server.endpoint].result().info.links()
    # What Zenoh made of the locator: a reliable, streamed link (QUIC streams) either way.
    assert str(link.reliability) == "Reliability.RELIABLE" and link.is_streamed
    assert str(link.dst) == locator(server.endpoint)
    assert link.auth_identifier in (None, "coapkb anonymous QUIC listener")  # nobody authenticated


async def test_reliable_udp_is_not_the_plain_udp_link() -> None:
    """``?rel=1`` is locator metadata: a client of Zenoh's plain UDP link
    (no ``rel``) never gets a session with the reliable-UDP listener."""
    async with await ZenohServerTransport.start(Counter(), Endpoint("zenoh+udp", "127.0.0.1", 0)) as server:
        plain = locator(server.endpoint).removesuffix("?rel=1")
        config = zenoh.Config()
        config.insert_json5("mode", '"client"')
        config.insert_json5("connect/endpoints", f'["{plain}"]')
        config.insert_json5("transport/unicast/open_timeout", "500")
        # as coapkb's own sessions: no scouting (binding its multicast socket
        # fails on a host whose interfaces the namespace tests have changed)
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("scouting/gossip/enabled", "false")
        with pytest.raises(zenoh.ZError, match="Unable to connect"):
            await asyncio.to_thread(zenoh.open, config)


# =========================================================================== with the team's keys


@pytest.fixture
async def robot1(team: Path):
    """Robot1 over QUIC with the team's mutual TLS; Robot2 decides."""
    service = Counter()
    security = server_security("zenoh+quic", load_identity(team, "Robot1"), AccessPolicy(lambda: {"Robot2"}))
    server = await serve(service, Endpoint("zenoh+quic", "127.0.0.1", 0), security=security)
    yield server, service
    await server.aclose()


async def _client(team: Path, name: str, expected: dict[str, str] | None = None):
    return await open_client("zenoh+quic", security=client_security("zenoh+quic", load_identity(team, name), expected))


async def test_request_and_observe_with_team_credentials(robot1, team: Path) -> None:
    server, service = robot1
    client = await _client(team, "Robot2", {server.endpoint.hostport: "Robot1"})
    try:
        answer = await client.request(server.endpoint, Request(Method.GET, "/counter"), timeout=5)
        assert (answer.status, answer.payload) == (Status.CONTENT, b"0")
        decided = await client.request(server.endpoint, Request(Method.POST, "/decisions", payload=b"x"), timeout=5)
        assert decided.status == Status.CHANGED
        assert await _observe_three(client, server.endpoint, service) == [b"0", b"1", b"2"]
    finally:
        await client.aclose()
    # The server named each request's sender from its QUIC link's certificate.
    assert {peer for _, _, peer in service.calls} == {"Robot2"}


async def test_the_team_policy_holds_over_quic(robot1, team: Path) -> None:
    """Zenoh's access control by certificate name and the team's policy per
    request, as over TLS: /tasks only for the feeder, /decisions only for the deciding robot."""
    server, service = robot1
    cases = [
        ("feeder", Method.POST, "/tasks", Status.CHANGED),
        ("Robot2", Method.POST, "/tasks", None),  # dropped by Zenoh's ACL: no answer at all
        ("Robot3", Method.POST, "/decisions", Status.FORBIDDEN),  # a robot, but not the deciding one
        ("operator", Method.GET, "/counter", Status.CONTENT),
    ]
    for who, method, path, expected in cases:
        client = await _client(team, who)
        try:
            request = Request(method, path, payload=b"x" if method == Method.POST else b"")
            if expected is None:
                with pytest.raises(PeerUnreachable, match=f"access control refuses {path}"):
                    await client.request(server.endpoint, request, timeout=2)
            else:
                assert (await client.request(server.endpoint, request, timeout=5)).status == expected, (who, path)
        finally:
            await client.aclose()
    assert [(m, p) for m, p, _ in service.calls] == [("POST", "/tasks"), ("GET", "/counter")]


async def test_nobody_without_a_team_certificate_gets_a_session(robot1, team: Path, tmp_path: Path) -> None:
    server, service = robot1
    options = ZenohOptions(open_timeout_s=1.0)
    anonymous = ZenohClientTransport(options=options)  # the public CA's trust, no certificate of its own
    other_team = tmp_path / "other"
    generate_team(other_team, default_members(3))
    stranger = ZenohClientTransport(options=options, security=client_security(
        "zenoh+quic", load_identity(other_team, "Robot2")))
    try:
        for client in (anonymous, stranger):
            with pytest.raises(PeerUnreachable, match="cannot reach zenoh\\+quic://"):
                await client.request(server.endpoint, Request(Method.GET, "/counter"), timeout=10)
    finally:
        await anonymous.aclose()
        await stranger.aclose()
    assert service.calls == []


async def test_a_member_does_not_accept_an_anonymous_listener_nor_the_wrong_member(robot1, team: Path) -> None:
    server, _ = robot1
    member = await _client(team, "Robot2", {server.endpoint.hostport: "Robot3"})
    try:
        with pytest.raises(PeerUnreachable, match="presented Robot1's certificate, not Robot3's"):
            await member.request(server.endpoint, Request(Method.GET, "/counter"), timeout=5)
    finally:
        await member.aclose()
    async with await ZenohServerTransport.start(Counter(), Endpoint("zenoh+quic", "127.0.0.1", 0)) as anonymous:
        member = ZenohClientTransport(options=ZenohOptions(open_timeout_s=1.0), security=client_security(
            "zenoh+quic", load_identity(team, "Robot2")))
        try:
            with pytest.raises(PeerUnreachable, match="over TLS with this team's certificates"):
                await member.request(anonymous.endpoint, Request(Method.GET, "/counter"), timeout=10)
        finally:
            await member.aclose()


async def test_reliable_udp_refuses_security(team: Path) -> None:
    """Asked for security, zenoh+udp refuses, saying why, before taking a port."""
    with pytest.raises(SecurityError, match="zenoh\\+udp transport cannot be secured: it is Zenoh's reliable UDP"):
        server_security("zenoh+udp", load_identity(team, "Robot1"))
    # The mechanism built for zenoh:// (TLS) handed a zenoh+udp endpoint anyway:
    tls = server_security("zenoh", load_identity(team, "Robot1"))
    with pytest.raises(SecurityError, match="reliable UDP, QUIC without encryption or authentication"):
        await serve(Counter(), Endpoint("zenoh+udp", "127.0.0.1", 0), security=tls)
    client = ZenohClientTransport(security=client_security("zenoh", load_identity(team, "feeder")))
    try:
        with pytest.raises(SecurityError, match="cannot be secured; use zenoh\\+quic://"):
            await client.request(Endpoint("zenoh+udp", "127.0.0.1", 1), Request(Method.GET, "/counter"), timeout=1)
    finally:
        await client.aclose()


# =========================================================================== an unreachable peer


@pytest.mark.parametrize("scheme", LINKS)
async def test_an_unreachable_peer_is_a_clear_transport_error(scheme: str) -> None:
    """Nothing listens: no refusal comes back over QUIC, so each attempt ends
    at the open timeout; the caller gets PeerUnreachable naming the peer."""
    peer = Endpoint(scheme, "127.0.0.1", free_udp_port())
    async with ZenohClientTransport(options=ZenohOptions(open_timeout_s=0.5)) as client:
        with pytest.raises(PeerUnreachable, match=re.escape(f"cannot reach {peer}: Unable to connect")) as caught:
            await client.request(peer, Request(Method.GET, "/counter"), timeout=10)
        assert isinstance(caught.value, TransportError)
        assert "\n" not in str(caught.value)  # one line, no Rust backtrace
        with pytest.raises(PeerUnreachable, match="within 0.3s"):  # the caller's own limit comes first
            await client.request(peer, Request(Method.GET, "/counter"), timeout=0.3)


# =========================================================================== from the command line


@pytest.mark.slow
async def test_serve_and_query_over_quic_from_the_command_line(team: Path) -> None:
    """``coapkb serve/query --transport zenoh+quic`` with and without the team's
    keys; a dead peer and a secured zenoh+udp are one line each, no traceback."""
    kbs = [str(ONTOLOGIES / f"{n}.owl") for n in ("Object", "Location", "Capability")]
    for credentials in (["--credentials", str(team)], []):
        server = await ServerProcess.start("--kb", *kbs, "--bind", f"127.0.0.1:{free_udp_port()}",
                                           "--transport", "zenoh+quic", *credentials)
        try:
            uri = f"{server.uri}/kb/q/object-exists?name=Gucci_bag_14"
            assert uri.startswith("zenoh+quic://")
            code, out, err = await coapkb("query", uri, *credentials, "--format", "json")
            assert code == 0 and "Gucci_bag_14" in out, err
            if credentials:  # a stranger (no keys: the anonymous QUIC trust) never gets a session
                code, out, err = await coapkb("query", uri, "--timeout", "3")
                assert code != 0 and "Traceback" not in err and "cannot reach" in err, err
        finally:
            await server.stop()
    dead = f"zenoh+quic://127.0.0.1:{free_udp_port()}/kb/q/object-exists?name=Gucci_bag_14"
    code, out, err = await coapkb("query", dead, "--timeout", "2")
    assert code != 0 and "Traceback" not in err, err
    assert err.splitlines() == [f"coapkb: no answer from {dead.split('/kb')[0]} within 2s"]
    code, out, err = await coapkb("serve", "--kb", *kbs, "--bind", f"127.0.0.1:{free_udp_port()}",
                                  "--transport", "zenoh+udp", "--credentials", str(team))
    assert code != 0 and "Traceback" not in err
    assert "zenoh+udp transport cannot be secured: it is Zenoh's reliable UDP" in err, err
