"""DDS transport: client and server on real UDP sockets on 127.0.0.1 (Cyclone
DDS with unicast discovery), in this process and against a real
``coapkb serve`` process.

What every transport does (requests, observe, dead peers, garbage at the
port, ...) is tests/transport/test_contract.py; here is what only DDS has:
its domains and topics, discovery, its samples' parser, a robot process.

Every test that waits for something waits on the thing itself (a response, an
event set by the service, a line printed by a child process), never on a sleep.
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import Callable

import pytest
from support import KB_FILES, ServerProcess, free_udp_port

from coapkb.transport import open_client, serve, transport_for
from coapkb.transport.base import Endpoint, PeerUnreachable, ResourceInfo, Service, TransportError
from coapkb.transport.dds.config import client_domain_xml, server_domain_xml, topic_names
from coapkb.transport.dds.envelope import Envelope
from coapkb.transport.dds.transport import DdsClientTransport, DdsOptions, DdsServerTransport
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status
from coapkb.transport.registry import parse_endpoint
from coapkb.wire.codec import decode_cbor

LOCAL = Endpoint("dds", "127.0.0.1", 0)


class DemoService(Service):
    """Echo and an observable counter (what the transport contract,
    tests/transport/test_contract.py, does not cover is DDS's own)."""

    def __init__(self) -> None:
        self.counter = 0
        self._subscribers: dict[int, Callable[[], None]] = {}
        self._next_sub = 0
        self.unsubscribed = asyncio.Event()

    def resources(self) -> list[ResourceInfo]:
        return [ResourceInfo("/echo"), ResourceInfo("/counter", obs=True)]

    async def handle(self, request: Request) -> Response:
        if request.path == "/echo":
            return Response(Status.CONTENT, b"echo:" + request.payload)
        if request.path == "/counter":
            return Response(Status.CONTENT, str(self.counter).encode(), ContentFormat.TEXT)
        return Response.error(Status.NOT_FOUND, f"no resource {request.path}")

    def subscribe(self, path: str, on_change: Callable[[], None]) -> Callable[[], None]:
        if path != "/counter":
            return lambda: None
        key = self._next_sub = self._next_sub + 1
        self._subscribers[key] = on_change

        def cancel() -> None:
            self._subscribers.pop(key, None)
            self.unsubscribed.set()

        return cancel


@pytest.fixture
def service() -> DemoService:
    return DemoService()


@pytest.fixture
async def server(service: DemoService):
    srv = await DdsServerTransport.start(service, LOCAL)
    yield srv
    await srv.aclose()


@pytest.fixture
async def client():
    cli = DdsClientTransport()
    yield cli
    await cli.aclose()


# =========================================================================== the mapping


def test_server_takes_discovery_and_data_on_its_one_port() -> None:
    xml = server_domain_xml("127.0.0.1", 7400)
    assert "<Base>7400</Base>" in xml and "<ParticipantIndex>0</ParticipantIndex>" in xml
    for gain_or_offset in ("DomainGain", "ParticipantGain", "UnicastMetaOffset", "UnicastDataOffset"):
        assert f"<{gain_or_offset}>0</{gain_or_offset}>" in xml
    assert "<AllowMulticast>false</AllowMulticast>" in xml and "<Peer " not in xml
    # The slow-radio settings (docs/dds.md): one frame per datagram, 1 s heartbeats, 30 s lease.
    assert "<MaxMessageSize>1472B</MaxMessageSize>" in xml
    assert "<HeartbeatInterval>1000ms</HeartbeatInterval>" in xml and "<LeaseDuration>30000ms</LeaseDuration>" in xml
    client = client_domain_xml("127.0.0.1", "127.0.0.1:7400")
    assert '<Peer Address="127.0.0.1:7400" PruneDelay="inf"/>' in client
    assert "<ParticipantIndex>none</ParticipantIndex>" in client
    with pytest.raises(ValueError):
        server_domain_xml("127.0.0.1", 0)


def test_topics_name_the_server_and_the_client() -> None:
    names = topic_names("10.0.0.2", 7400, 0xAB)
    assert names.requests == "coapkb_rq_10_0_0_2_7400"
    assert names.replies == "coapkb_rp_10_0_0_2_7400_00000000000000ab"
    assert names.notifications == "coapkb_nt_10_0_0_2_7400_00000000000000ab"


def test_registry_refuses_security_and_says_why() -> None:
    dds = transport_for("dds")
    assert dds.security is None and dds.datagram and dds.retransmits_itself
    assert "no DDS Security plugins" in (dds.unsecurable_because or "")


# =========================================================================== requests


async def test_client_started_before_its_server_finds_it(service, client) -> None:
    """The client's first SPDP goes nowhere (nobody listens yet); it re-announces
    itself while it waits, instead of waiting for Cyclone's next one (30 s)."""
    peer = Endpoint("dds", "127.0.0.1", free_udp_port())
    waiting = asyncio.create_task(client.request(peer, Request(Method.GET, "/echo"), timeout=20))
    link = client._link(peer)
    await asyncio.wait_for(_announced(link), 10)  # it has been re-announcing already
    async with await DdsServerTransport.start(service, peer):
        response = await waiting
    assert response.status is Status.CONTENT


async def _announced(link) -> None:
    while next(link.participant._userdata) < 3:  # at least one re-announcement (the counter moves on)
        await asyncio.sleep(0.1)


# =========================================================================== unreachable peers


async def test_dead_peer_is_unreachable_at_the_timeout(client) -> None:
    peer = Endpoint("dds", "127.0.0.1", free_udp_port())
    with pytest.raises(PeerUnreachable, match=rf"no DDS participant discovered at {peer} within 1s"):
        await asyncio.wait_for(client.request(peer, Request(Method.GET, "/echo"), timeout=1.0), 5)


async def test_port_in_use_is_a_transport_error(server, service) -> None:
    """Kept while the contract's case is an expected failure on DDS (its message says nothing of the port in use)."""
    with pytest.raises(TransportError, match="cannot serve"):
        await DdsServerTransport.start(service, server.endpoint)


# =========================================================================== bad input


async def test_garbage_samples_do_not_kill_the_server(server, client) -> None:
    """Well-formed DDS samples whose envelope is not a coapkb request:
    counted, dropped.  (Datagrams that are not RTPS, which Cyclone drops,
    are the transport contract's.)"""
    await client.request(server.endpoint, Request(Method.GET, "/echo"), timeout=10)
    rogue = DdsClientTransport()
    try:
        link = rogue._link(server.endpoint)
        await asyncio.wait_for(link.discovered(), 10)
        for body in (b"", b"\xff\xfe", b"\x83\x01\x02\x03", os.urandom(50)):
            link.requests.write(Envelope(id=rogue.id, body=body))
        ok = await rogue.request(server.endpoint, Request(Method.GET, "/echo"), timeout=10)
        assert ok.status is Status.CONTENT  # after the garbage, in order: it was all taken
    finally:
        await rogue.aclose()
    assert server.malformed == 4
    response = await client.request(server.endpoint, Request(Method.GET, "/echo"), timeout=10)
    assert response.status is Status.CONTENT


# =========================================================================== observe


async def test_observer_whose_participant_closes_is_forgotten(server, service) -> None:
    cli = DdsClientTransport()
    updates = cli.observe(server.endpoint, Request(Method.GET, "/counter"))
    assert (await anext(updates)).payload == b"0"
    assert server.observation_count == 1
    await cli.aclose()  # no deregistration: the participant just goes away
    await asyncio.wait_for(service.unsubscribed.wait(), 10)  # the server saw its reader go
    assert server.observation_count == 0
    await updates.aclose()


async def test_observe_cap(service, client) -> None:
    async with await DdsServerTransport.start(service, LOCAL, options=DdsOptions(max_observations=1)) as srv:
        first = client.observe(srv.endpoint, Request(Method.GET, "/counter"))
        await anext(first)
        extra = [r async for r in client.observe(srv.endpoint, Request(Method.GET, "/counter"))]
        assert [r.payload for r in extra] == [b"0"]  # answered, not registered: the iterator ends
        await first.aclose()


# =========================================================================== a real robot process


async def test_named_query_to_a_serve_process_and_its_restart() -> None:
    port = free_udp_port()
    args = ("--kb", *KB_FILES, "--bind", f"127.0.0.1:{port}", "--transport", "dds")
    robot = await ServerProcess.start(*args)
    peer = parse_endpoint(robot.uri)
    assert peer == Endpoint("dds", "127.0.0.1", port)
    client = await open_client("dds")
    try:
        named = Request(Method.GET, "/kb/q/object-location", {"name": "Gucci_bag_14"}, accept=ContentFormat.CBOR)
        response = await client.request(peer, named, timeout=10)
        assert response.status is Status.CONTENT and response.content_format == ContentFormat.CBOR
        assert len(decode_cbor(response.payload).rows) == 1
        await robot.stop()
        with pytest.raises(PeerUnreachable):
            await client.request(peer, named, timeout=0.5)
        robot = await ServerProcess.start(*args)  # a new participant on the same port: rediscovered
        again = await client.request(peer, named, timeout=20)
        assert again.payload == response.payload
    finally:
        await client.aclose()
        await robot.stop()


async def test_serve_factory_picks_dds(service) -> None:
    srv = await serve(service, Endpoint("dds", "127.0.0.1", 0))
    try:
        assert isinstance(srv, DdsServerTransport)
    finally:
        await srv.aclose()
