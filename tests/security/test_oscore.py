"""OSCORE keyed by EDHOC on real UDP sockets: who gets in, what they may do,
replays, a server that lost its contexts, Block-wise and Observe."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
from collections.abc import AsyncIterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from support import observation_count, until

from coapkb.security import AccessPolicy, TeamIdentity, TeamTrust, generate_team, load_identity
from coapkb.security.coap import ClientSecurity, EdhocFailed, ServerSecurity
from coapkb.security.keys import default_members
from coapkb.transport import Endpoint, open_client, serve
from coapkb.transport.base import ClientTransport, PeerUnreachable, ResourceInfo
from coapkb.transport.messages import Method, Request, Response, Status
from coapkb.transport.router import Router

BIG = bytes(range(256)) * 12  # three Block2 blocks of 1024


class Robot1:
    """A server with Robot1's identity; counts what reached its resources."""

    def __init__(self, team_dir: Path) -> None:
        self.team_dir = team_dir
        self.calls: list[tuple[str, str]] = []
        self.state = 0
        self.router = Router()
        self.router.add(ResourceInfo("/tasks", methods=("GET", "POST")), self._handle)
        self.router.add(ResourceInfo("/decisions", methods=("POST",)), self._handle)
        self.router.add(ResourceInfo("/big"), self._handle)
        self.router.add(ResourceInfo("/state", obs=True), self._handle)
        self.router.add(ResourceInfo("/kb", methods=("GET", "PATCH", "iPATCH")), self._handle)
        self.router.add(ResourceInfo("/kb/sync", methods=("POST",)), self._handle)
        self.server = None

    async def _handle(self, request: Request) -> Response:
        self.calls.append((str(request.method), request.path))
        if request.path == "/big":
            return Response(Status.CONTENT, BIG)
        if request.path == "/state":
            return Response(Status.CONTENT, str(self.state).encode())
        return Response(Status.CONTENT if request.method == Method.GET else Status.CHANGED, b"ok")

    async def start(self, port: int = 0) -> Endpoint:
        # Robot2 decides for this robot's cluster.
        security = ServerSecurity(load_identity(self.team_dir, "Robot1"), AccessPolicy(lambda: {"Robot2"}))
        self.server = await serve(self.router, Endpoint("coap", "127.0.0.1", port), security=security)
        return self.server.endpoint

    async def stop(self) -> None:
        await self.server.aclose()


@pytest.fixture
async def robot1(team_dir: Path) -> AsyncIterator[tuple[Robot1, Endpoint]]:
    robot = Robot1(team_dir)
    endpoint = await robot.start()
    yield robot, endpoint
    await robot.stop()


async def _client(identity: TeamIdentity | None):
    return await open_client("coap", security=None if identity is None else ClientSecurity(identity))


async def _ask(identity: TeamIdentity | None, peer: Endpoint, method: Method, path: str) -> Response:
    client = await _client(identity)
    try:
        return await client.request(peer, Request(method, path, payload=b"" if method == Method.GET else b"x"),
                                    timeout=5)
    finally:
        await client.aclose()


async def test_without_oscore_every_resource_is_4_01_and_nothing_changes(robot1) -> None:
    robot, peer = robot1
    for method, path in [(Method.GET, "/tasks"), (Method.POST, "/tasks"), (Method.POST, "/decisions"),
                         (Method.GET, "/state")]:
        response = await _ask(None, peer, method, path)
        assert response.status == Status.UNAUTHORIZED, (method, path)
    assert robot.calls == []


async def test_discovery_stays_open(robot1) -> None:
    _, peer = robot1
    response = await _ask(None, peer, Method.GET, "/.well-known/core")
    assert response.status == Status.CONTENT and b"</tasks>" in response.payload


async def test_each_role_may_do_what_the_policy_says(robot1, team_dir: Path) -> None:
    robot, peer = robot1
    me = {name: load_identity(team_dir, name) for name in ("feeder", "Robot2", "Robot3", "operator")}
    cases = [
        ("feeder", Method.POST, "/tasks", Status.CHANGED),
        ("Robot2", Method.POST, "/tasks", Status.FORBIDDEN),
        ("operator", Method.POST, "/tasks", Status.FORBIDDEN),
        ("Robot2", Method.POST, "/decisions", Status.CHANGED),  # the decider
        ("Robot3", Method.POST, "/decisions", Status.FORBIDDEN),
        ("feeder", Method.POST, "/decisions", Status.FORBIDDEN),
        ("Robot3", Method.GET, "/tasks", Status.CONTENT),
        ("operator", Method.GET, "/tasks", Status.CONTENT),
    ]
    for who, method, path, expected in cases:
        response = await _ask(me[who], peer, method, path)
        assert response.status == expected, (who, method, path, response)
    assert robot.calls == [("POST", "/tasks"), ("POST", "/decisions"), ("GET", "/tasks"), ("GET", "/tasks")]


async def test_writes_to_the_kb_by_role(robot1, team_dir: Path) -> None:
    """The operator and robots write the KB; only robots replicate; the feeder writes nothing."""
    robot, peer = robot1
    me = {name: load_identity(team_dir, name) for name in ("feeder", "Robot3", "operator")}
    cases = [
        ("operator", Method.PATCH, "/kb", Status.CHANGED),
        ("Robot3", Method.IPATCH, "/kb", Status.CHANGED),
        ("feeder", Method.PATCH, "/kb", Status.FORBIDDEN),
        ("Robot3", Method.POST, "/kb/sync", Status.CHANGED),
        ("operator", Method.POST, "/kb/sync", Status.FORBIDDEN),
        ("feeder", Method.POST, "/kb/sync", Status.FORBIDDEN),
        ("feeder", Method.GET, "/kb", Status.CONTENT),
    ]
    for who, method, path, expected in cases:
        response = await _ask(me[who], peer, method, path)
        assert response.status == expected, (who, method, path, response)
    assert (await _ask(None, peer, Method.PATCH, "/kb")).status == Status.UNAUTHORIZED
    assert robot.calls == [("PATCH", "/kb"), ("iPATCH", "/kb"), ("POST", "/kb/sync"), ("GET", "/kb")]


async def test_a_credential_not_in_the_trust_list_is_refused(robot1, team_dir: Path, tmp_path: Path) -> None:
    """An outsider (its own valid key, not in Robot1's trust list) cannot finish EDHOC."""
    robot, peer = robot1
    generate_team(tmp_path / "other", default_members(3) + [("intruder", "feeder")])
    intruder = load_identity(tmp_path / "other", "intruder")
    ours = load_identity(team_dir, "feeder").trust
    # It even knows our trust list (so it accepts Robot1); Robot1 does not know it.
    outsider = replace(intruder, trust=TeamTrust(ours.members + (intruder.member,)))
    with pytest.raises(EdhocFailed, match="refused"):
        await _ask(outsider, peer, Method.POST, "/tasks")
    assert robot.calls == []


async def test_a_team_name_with_the_wrong_key_is_refused(robot1, team_dir: Path, tmp_path: Path) -> None:
    """Claiming to be the feeder (its key id) without the feeder's private key."""
    robot, peer = robot1
    generate_team(tmp_path / "other", default_members(3))
    impostor = replace(load_identity(team_dir, "feeder"), private_d=load_identity(tmp_path / "other", "feeder").private_d)
    with pytest.raises(EdhocFailed):
        await _ask(impostor, peer, Method.POST, "/tasks")
    assert robot.calls == []


async def test_a_server_with_another_key_is_not_trusted(team_dir: Path, tmp_path: Path) -> None:
    """The client side too: a server whose credential is not the team's is refused."""
    generate_team(tmp_path / "other", default_members(3))
    fake = Robot1(tmp_path / "other")
    peer = await fake.start()
    try:
        with pytest.raises(EdhocFailed):
            await _ask(load_identity(team_dir, "feeder"), peer, Method.GET, "/tasks")
    finally:
        await fake.stop()


class _Relay(asyncio.DatagramProtocol):
    """A UDP relay between one client and the server that keeps every datagram the client sent."""

    def __init__(self, server: tuple[str, int]) -> None:
        self.server = server
        self.client: tuple[str, int] | None = None
        self.sent: list[bytes] = []

    def connection_made(self, transport) -> None:  # type: ignore[override]
        self.transport = transport

    def datagram_received(self, data: bytes, addr) -> None:  # type: ignore[override]
        if addr[:2] == self.server:
            if self.client is not None:
                self.transport.sendto(data, self.client)
        else:
            self.client = addr
            self.sent.append(data)
            self.transport.sendto(data, self.server)


def _has_oscore_option(datagram: bytes) -> bool:
    token_length = datagram[0] & 0x0F
    return len(datagram) > 4 + token_length and datagram[4 + token_length] >> 4 == 9  # first option: 9 (OSCORE)


async def test_a_replayed_request_is_refused(robot1, team_dir: Path) -> None:
    """The exact datagram of a protected POST, sent again from another socket
    (so CoAP's message deduplication does not catch it): OSCORE's replay
    window refuses it (a NON request gets no answer), and the resource is not called again."""
    robot, peer = robot1
    loop = asyncio.get_running_loop()
    transport, relay = await loop.create_datagram_endpoint(lambda: _Relay(("127.0.0.1", peer.port)),
                                                           local_addr=("127.0.0.1", 0))
    via = Endpoint("coap", "127.0.0.1", transport.get_extra_info("sockname")[1])
    client = await _client(load_identity(team_dir, "feeder"))
    try:
        assert (await client.request(via, Request(Method.GET, "/tasks"), timeout=5)).status == Status.CONTENT
        relay.sent.clear()
        response = await client.request(via, Request(Method.POST, "/tasks", payload=b"task 1"), timeout=5)
        assert response.status == Status.CHANGED
        captured = [d for d in relay.sent if _has_oscore_option(d)]
        assert len(captured) == 1
        assert robot.calls == [("GET", "/tasks"), ("POST", "/tasks")]
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as attacker:
            attacker.sendto(captured[0], ("127.0.0.1", peer.port))
        # A request sent after the replay, answered: the server read the replay first, and refused it.
        assert (await client.request(peer, Request(Method.GET, "/tasks"), timeout=5)).status == Status.CONTENT
        assert robot.calls == [("GET", "/tasks"), ("POST", "/tasks"), ("GET", "/tasks")]
    finally:
        await client.aclose()
        transport.close()


async def test_a_restarted_server_is_rekeyed(team_dir: Path) -> None:
    """The server loses every context (a restart on the same port): the
    client's next request gets 4.01, it runs EDHOC again and goes on."""
    robot = Robot1(team_dir)
    peer = await robot.start()
    client = await _client(load_identity(team_dir, "feeder"))
    try:
        assert (await client.request(peer, Request(Method.GET, "/tasks"), timeout=5)).status == Status.CONTENT
        await robot.stop()
        await robot.start(peer.port)
        async with asyncio.timeout(3):  # no waiting out a timeout: the 4.01 comes at once
            response = await client.request(peer, Request(Method.POST, "/tasks", payload=b"t"), timeout=5)
        assert response.status == Status.CHANGED
        assert len(client.security.handshakes) == 2
    finally:
        await client.aclose()
        await robot.stop()


async def test_a_restarted_server_that_gave_our_key_id_away_is_rekeyed(team_dir: Path) -> None:
    """The restarted server hands the connection identifier our old context
    used to another client (it picks the lowest free one, as before), so our
    requests no longer decrypt there.  The server says so (an unprotected
    4.01, as for a context it does not have) and the request runs EDHOC
    again at once, instead of timing out."""
    robot = Robot1(team_dir)
    peer = await robot.start()
    stale = await _client(load_identity(team_dir, "Robot2"))
    others = []
    try:
        assert (await stale.request(peer, Request(Method.GET, "/tasks"), timeout=5)).status == Status.CONTENT
        old_id = stale.security.context(stale._ctx, peer).sender_id
        await robot.stop()
        await robot.start(peer.port)
        # Other members key in until one is given our old identifier: the
        # first, unless a busy machine made a handshake's first message go
        # twice (each try a new exchange: the server keyed both).
        for name in ("Robot3", "feeder", "central", "operator"):
            other = await _client(load_identity(team_dir, name))
            others.append(other)
            assert (await other.request(peer, Request(Method.GET, "/tasks"), timeout=5)).status == Status.CONTENT
            if other.security.context(other._ctx, peer).sender_id == old_id:
                break
        else:
            pytest.fail(f"no other member was given identifier {old_id!r}")
        assert (await stale.request(peer, Request(Method.GET, "/tasks"), timeout=5)).status == Status.CONTENT
        assert len(stale.security.handshakes) == 2
    finally:
        await stale.aclose()
        for other in others:
            await other.aclose()
        await robot.stop()


@contextlib.asynccontextmanager
async def _keyed_then_silent(team_dir: Path) -> AsyncIterator[tuple[ClientTransport, Endpoint, socket.socket, Any]]:
    """Robot2's client, keyed with Robot1, whose port then reads and drops
    everything: the client, Robot1's endpoint, that socket, and the
    client's OSCORE request interface."""
    from coapkb.security.coap import _OSCORETransport

    robot = Robot1(team_dir)
    peer = await robot.start()
    client = await _client(load_identity(team_dir, "Robot2"))
    silent = None
    try:
        assert (await client.request(peer, Request(Method.GET, "/tasks"), timeout=5)).status == Status.CONTENT
        await robot.stop()
        silent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        silent.bind((peer.host, peer.port))
        silent.setblocking(False)
        (oscore,) = [i for i in client._ctx.request_interfaces if isinstance(i, _OSCORETransport)]
        yield client, peer, silent, oscore
    finally:
        await client.aclose()
        if silent is not None:
            silent.close()


async def test_abandoned_tries_leave_no_task_or_token_behind(team_dir: Path) -> None:
    """Every NON try the robust layer gives up ends its OSCORE task and frees
    its token (aiocoap kept both until the context shut down: a slow leak
    for a robot that runs for days)."""
    async with _keyed_then_silent(team_dir) as (client, peer, _silent, oscore):
        with pytest.raises(PeerUnreachable):  # several NON tries, each its own OSCORE request
            await client.request(peer, Request(Method.GET, "/tasks"), timeout=2)
        async with asyncio.timeout(2):  # they end at once; before, they never did
            await asyncio.gather(*list(oscore._tasks), return_exceptions=True)
        assert not oscore._tasks


async def test_an_oscore_request_cancelled_at_the_loops_end_fails_without_a_traceback(team_dir: Path) -> None:
    """Ctrl-C cancels every task, aiocoap's OSCORE request tasks among them;
    their done-callback handles only ``Exception``, and the cancellation
    was logged as a traceback at a team's interruption."""
    loop = asyncio.get_running_loop()
    unhandled: list[dict[str, object]] = []
    loop.set_exception_handler(lambda _loop, context: unhandled.append(context))
    try:
        async with _keyed_then_silent(team_dir) as (client, peer, silent, oscore):
            asking = asyncio.create_task(client.request(peer, Request(Method.GET, "/tasks"), timeout=5))
            async with asyncio.timeout(5):
                await loop.sock_recv(silent, 2048)  # the request is on the wire: its OSCORE task waits
            in_flight = list(oscore._tasks)
            assert in_flight
            for task in in_flight:
                task.cancel()
            # Each task's own done-callbacks run before gather's, registered later.
            await asyncio.gather(*in_flight, return_exceptions=True)
            asking.cancel()
            await asyncio.gather(asking, return_exceptions=True)
        assert unhandled == []
    finally:
        loop.set_exception_handler(None)


async def test_blockwise_and_observe_over_oscore(robot1, team_dir: Path) -> None:
    robot, peer = robot1
    client = await _client(load_identity(team_dir, "Robot3"))
    try:
        big = await client.request(peer, Request(Method.GET, "/big"), timeout=5)
        assert big.status == Status.CONTENT and big.payload == BIG
        seen = []
        stream = client.observe(peer, Request(Method.GET, "/state"))
        async with asyncio.timeout(5):
            async for notification in stream:
                seen.append(notification.payload)
                if len(seen) == 3:
                    break
                robot.state += 1
                robot.router.notify("/state")
        await stream.aclose()
        assert seen == [b"0", b"1", b"2"]
        assert len(client.security.handshakes) == 1
    finally:
        await client.aclose()


async def _changes_until_forgotten(robot: Robot1, client: ClientTransport) -> None:
    """Change the robot's /state, each time once the client has the last
    notification, until its server holds no observation: a notification or
    two already on their way are taken, the next meets the client's Reset
    (RFC 7641 section 3.6).  Fails if one is kept."""
    async with asyncio.timeout(10):  # a kept observation fails the test, never hangs it
        while observation_count(robot.server):
            heard = client.counters.messages_received
            robot.state += 1
            robot.router.notify("/state")
            await until(lambda heard=heard: client.counters.messages_received > heard or not observation_count(robot.server),
                        "the notification reaches the client", timeout=5)


async def test_an_abandoned_observation_ends_on_the_wire(robot1, team_dir: Path) -> None:
    """aiocoap's OSCORE client cannot cancel an observation: the server kept
    notifying (and the client acknowledging) every abandoned registration.
    Now a notification meets a Reset and the server forgets it."""
    robot, peer = robot1
    client = await _client(load_identity(team_dir, "Robot3"))
    try:
        stream = client.observe(peer, Request(Method.GET, "/state"))
        assert (await anext(stream)).payload == b"0"
        await stream.aclose()
        assert observation_count(robot.server) == 1
        await _changes_until_forgotten(robot, client)
        sent = robot.server.counters.messages_sent
        for _ in range(8):
            robot.state += 1
            robot.router.notify("/state")
        assert robot.server.counters.messages_sent == sent  # nobody to notify
    finally:
        await client.aclose()


def test_the_aiocoap_internals_used_are_there() -> None:
    """coapkb.security relies on a few of aiocoap 0.4.17's OSCORE internals; an upgrade fails here first."""
    from coapkb.security.coap import verify

    verify()


async def test_registrations_abandoned_before_their_answer_end_too(robot1, team_dir: Path) -> None:
    """The robust layer's registration tries that lose the race are dropped
    before their answer comes: those observations must end as well (they
    leaked, and the peer notified each for ever: 18 notifications here)."""
    from coapkb.transport.coap.client import _abandon
    from coapkb.transport.coap.mapping import message_from_request

    robot, peer = robot1
    client = await _client(load_identity(team_dir, "Robot3"))
    try:
        await client.request(peer, Request(Method.GET, "/tasks"), timeout=5)  # EDHOC first
        sent = client.counters.messages_sent
        tries = [client._ctx.request(message_from_request(peer, Request(Method.GET, "/state"), observe=True),
                                     handle_blockwise=False) for _ in range(3)]
        await until(lambda: client.counters.messages_sent >= sent + 3, "the three registrations are sent")
        for pending in tries:
            _abandon(pending)
        await until(lambda: observation_count(robot.server) == 3, "the three registrations reach the robot")
        await _changes_until_forgotten(robot, client)
    finally:
        await client.aclose()


async def test_a_flood_of_edhoc_message_1_leaves_teammates_keyed_and_its_sessions_bounded(team_dir: Path) -> None:
    """Strangers' message_1 (anyone on the link can send one) open half-open
    sessions: at most HALF_OPEN_MAX are kept, and a teammate's complete
    session is never pushed out by them."""
    import cbor2
    import lakers
    from aiocoap import NON, POST, Message

    from coapkb.security import coap as oscore_layer

    robot = Robot1(team_dir)
    security = ServerSecurity(load_identity(team_dir, "Robot1"), AccessPolicy(lambda: {"Robot2"}))
    robot.server = await serve(robot.router, Endpoint("coap", "127.0.0.1", 0), security=security)
    peer = robot.server.endpoint
    teammate = await _client(load_identity(team_dir, "Robot3"))
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stranger.bind(("127.0.0.1", 0))
    stranger.setblocking(False)
    loop = asyncio.get_running_loop()
    try:
        assert (await teammate.request(peer, Request(Method.GET, "/tasks"), timeout=5)).status == Status.CONTENT
        assert security.responder_sessions() == (0, 1)
        for mid in range(1, 201):
            message_1 = lakers.EdhocInitiator().prepare_message_1(bytes([mid % 24]))
            flood = Message(code=POST, uri_path=(".well-known", "edhoc"), payload=cbor2.dumps(True) + message_1)
            flood.mtype, flood.mid, flood.token = NON, mid, mid.to_bytes(2, "big")
            await loop.sock_sendto(stranger, flood.encode(), ("127.0.0.1", peer.port))
            await asyncio.wait_for(loop.sock_recv(stranger, 2048), 10)  # its message_2
        half_open, complete = security.responder_sessions()
        assert half_open <= oscore_layer.HALF_OPEN_MAX and complete == 1
        # The teammate's session is the one it keyed before the flood: no new EDHOC.
        sent = teammate.counters.messages_sent
        assert (await teammate.request(peer, Request(Method.GET, "/tasks"), timeout=5)).status == Status.CONTENT
        assert teammate.counters.messages_sent - sent == 1
    finally:
        stranger.close()
        await teammate.aclose()
        await robot.stop()


async def test_when_identifiers_run_short_the_least_recently_used_member_keys_again(
    team_dir: Path
) -> None:
    """A server with more members talking to it than connection identifiers
    drops the session used least recently, and that member keys again on its
    next request (here with room for two)."""
    robot = Robot1(team_dir)
    security = ServerSecurity(load_identity(team_dir, "Robot1"), AccessPolicy(lambda: {"Robot2"}),
                              responder_identifiers=2)
    robot.server = await serve(robot.router, Endpoint("coap", "127.0.0.1", 0), security=security)
    peer = robot.server.endpoint
    clients = {name: await _client(load_identity(team_dir, name)) for name in ("Robot2", "Robot3", "feeder")}

    async def ask(name: str) -> int:
        """Messages ``name`` sent for one request (1: its session was still there)."""
        sent = clients[name].counters.messages_sent
        response = await clients[name].request(peer, Request(Method.GET, "/tasks"), timeout=5)
        assert response.status == Status.CONTENT
        return clients[name].counters.messages_sent - sent

    try:
        assert await ask("Robot2") > 1 and await ask("Robot3") > 1  # each keys once
        assert await ask("Robot2") == 1
        assert await ask("feeder") > 1  # no room left: Robot3's session, the least recently used, goes
        assert security.responder_sessions() == (0, 2)
        assert await ask("Robot2") == 1
        assert await ask("Robot3") > 1  # its session was gone: it keys again
    finally:
        for client in clients.values():
            await client.aclose()
        await robot.stop()


async def test_a_server_keys_with_more_members_than_cbor_integer_identifiers(tmp_path: Path) -> None:
    """A central server for 60 robots: every member keys once and stays
    keyed (aiocoap alone has 48 one-byte integer identifiers and answered
    the 48th member 5.00).  Identifiers beyond them are one-byte byte strings."""
    from coapkb.security import coap as oscore_layer

    team = tmp_path / "team"
    generate_team(team, default_members(60))
    robot = Robot1(team)
    security = ServerSecurity(load_identity(team, "central"), AccessPolicy())
    robot.server = await serve(robot.router, Endpoint("coap", "127.0.0.1", 0), security=security)
    peer = robot.server.endpoint
    names = [f"Robot{i}" for i in range(1, 61)]
    clients = {name: await _client(load_identity(team, name)) for name in names}
    try:
        first = await asyncio.gather(*(clients[n].request(peer, Request(Method.GET, "/tasks"), timeout=10) for n in names))
        assert all(r.status == Status.CONTENT for r in first)
        half_open, complete = security.responder_sessions()
        # On a busy machine a client's message_1 may go again before its
        # message_2 came: the copy is a half-open session of its own, never more.
        retried = sum(c.counters.retransmissions for c in clients.values())
        assert complete == 60 and half_open <= retried, (half_open, retried)
        sent = {n: clients[n].counters.messages_sent - clients[n].counters.retransmissions for n in names}
        for name in names:  # every session still there: one message each, no new handshake
            assert (await clients[name].request(peer, Request(Method.GET, "/tasks"), timeout=5)).status == Status.CONTENT
            # A try sent again on a busy machine is the same message, not a handshake.
            counters = clients[name].counters
            assert counters.messages_sent - counters.retransmissions - sent[name] == 1
        assert oscore_layer.RESPONDER_IDENTIFIERS > 60
    finally:
        for client in clients.values():
            await client.aclose()
        await robot.stop()


def _message_1(mid: int) -> bytes:
    """A stranger's EDHOC message_1 as a NON POST (anyone can make one)."""
    import cbor2
    import lakers
    from aiocoap import NON, POST, Message

    message_1 = lakers.EdhocInitiator().prepare_message_1(bytes([mid % 24]))
    flood = Message(code=POST, uri_path=(".well-known", "edhoc"), payload=cbor2.dumps(True) + message_1)
    flood.mtype, flood.mid, flood.token = NON, mid, mid.to_bytes(2, "big")
    return flood.encode()


async def test_strangers_traffic_leaves_teammates_answered_and_the_responder_state_bounded_and_aging(
    team_dir: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """While three teammates keep asking, strangers on 50 source ports send
    EDHOC message_1 beyond the responder's rate, a teammate's protected
    request replayed, truncated and with unknown key ids: every teammate's
    request is answered, the half-open sessions stay within HALF_OPEN_MAX and
    age out, the rest of the message_1 are told 5.03 with Max-Age, and nothing
    is logged as an error."""
    from aiocoap import Message

    from coapkb.security import coap as oscore_layer

    robot = Robot1(team_dir)
    security = ServerSecurity(load_identity(team_dir, "Robot1"), AccessPolicy(lambda: {"Robot2"}))
    robot.server = await serve(robot.router, Endpoint("coap", "127.0.0.1", 0), security=security)
    peer = robot.server.endpoint
    loop = asyncio.get_running_loop()
    transport, relay = await loop.create_datagram_endpoint(lambda: _Relay(("127.0.0.1", peer.port)),
                                                           local_addr=("127.0.0.1", 0))
    via = Endpoint("coap", "127.0.0.1", transport.get_extra_info("sockname")[1])
    teammates = {name: await _client(load_identity(team_dir, name)) for name in ("Robot2", "Robot3", "feeder")}
    strangers = []
    for _ in range(50):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        s.setblocking(False)
        strangers.append(s)
    answered: list[Status] = []
    flooding = True

    async def keep_asking(name: str) -> None:
        client = teammates[name]
        target = via if name == "feeder" else peer  # the feeder's datagrams are captured on the way
        while flooding:
            answered.append((await client.request(target, Request(Method.GET, "/tasks"), timeout=10)).status)

    try:
        for client in teammates.values():  # keyed before the strangers come
            assert (await client.request(peer, Request(Method.GET, "/tasks"), timeout=5)).status == Status.CONTENT
        askers = [asyncio.create_task(keep_asking(name)) for name in teammates]
        while not [d for d in relay.sent if _has_oscore_option(d)]:
            await asyncio.sleep(0.01)  # until the feeder's first protected request went through the relay
        protected = [d for d in relay.sent if _has_oscore_option(d)][0]
        replies = 0
        taken_before = security.taken_starts
        flood_started = loop.time()
        for mid in range(1, 401):
            stranger = strangers[mid % len(strangers)]
            await loop.sock_sendto(stranger, _message_1(mid), ("127.0.0.1", peer.port))
            await loop.sock_sendto(stranger, protected, ("127.0.0.1", peer.port))  # a replay
            await loop.sock_sendto(stranger, protected[: mid % len(protected)], ("127.0.0.1", peer.port))  # cut
            seen = Message.decode(protected)
            unknown = Message(code=seen.code, payload=seen.payload)
            unknown.opt.oscore = bytes([0x09, mid % 256]) + b"\xee" * 6  # a partial IV and a key id nobody has
            unknown.mtype, unknown.mid, unknown.token = seen.mtype, mid, seen.token
            await loop.sock_sendto(stranger, unknown.encode(), ("127.0.0.1", peer.port))
            if mid % 20 == 0:
                await asyncio.sleep(0.02)  # let the teammates' requests in between
        for stranger in strangers:
            while True:
                try:
                    stranger.recv(2048)
                    replies += 1
                except BlockingIOError:
                    break
        flooding = False
        await asyncio.gather(*askers)
        assert answered and set(answered) == {Status.CONTENT}
        half_open, complete = security.responder_sessions()
        assert half_open <= oscore_layer.HALF_OPEN_MAX and complete == 3
        # The bucket takes on its burst and what refilled while the flood
        # lasted (longer on a loaded machine); every other message_1 that
        # reached the server was refused.  How many reached it, and so how
        # many were refused, depends on the machine: the kernel drops what a
        # busy server has not read in time, and a slow flood refills.
        refilled = oscore_layer.EDHOC_STARTS_PER_S * (loop.time() - flood_started)
        assert security.taken_starts - taken_before <= oscore_layer.HALF_OPEN_MAX + refilled + 1
        assert replies > 0
        security.sweep(loop.time() + oscore_layer.HALF_OPEN_S)  # the server's periodic sweep once that age has passed
        assert security.responder_sessions() == (0, 3)
        # No replay reached the resource.  A teammate's try the loaded server
        # answered late is sent again as a new OSCORE request (a GET is safe),
        # so each counted retry may add one call.
        retries = sum(client.counters.retransmissions for client in teammates.values())
        assert len(answered) + 3 <= robot.calls.count(("GET", "/tasks")) <= len(answered) + 3 + retries
        assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
    finally:
        flooding = False
        for s in strangers:
            s.close()
        for client in teammates.values():
            await client.aclose()
        transport.close()
        await robot.stop()


async def test_a_member_told_to_come_back_later_keys_when_it_does(team_dir: Path) -> None:
    """Strangers took every message_1 the responder takes on for now: a
    member's first contact is told 5.03 with Max-Age, waits, and keys."""
    robot = Robot1(team_dir)
    security = ServerSecurity(load_identity(team_dir, "Robot1"), AccessPolicy(lambda: {"Robot2"}))
    robot.server = await serve(robot.router, Endpoint("coap", "127.0.0.1", 0), security=security)
    peer = robot.server.endpoint
    loop = asyncio.get_running_loop()
    member = await _client(load_identity(team_dir, "Robot3"))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as stranger:
        stranger.bind(("127.0.0.1", 0))
        stranger.setblocking(False)
        try:
            from coapkb.security import coap as oscore_layer

            for mid in range(1, 10 * oscore_layer.HALF_OPEN_MAX):  # the bucket refills as they go
                await loop.sock_sendto(stranger, _message_1(mid), ("127.0.0.1", peer.port))
                reply = await asyncio.wait_for(loop.sock_recv(stranger, 2048), 10)
                if reply[1] == 0xA3:  # 5.03: no more for now
                    break
            assert security.refused_starts >= 1
            started = loop.time()
            response = await member.request(peer, Request(Method.GET, "/tasks"), timeout=15)
            assert response.status == Status.CONTENT
            assert loop.time() - started < 10
        finally:
            await member.aclose()
            await robot.stop()
