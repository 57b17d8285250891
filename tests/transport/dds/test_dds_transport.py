"""DDS transport: client and server on real UDP sockets on 127.0.0.1 (Cyclone
DDS with unicast discovery), in this process and against a real
``coapkb serve`` process.

Every test that waits for something waits on the thing itself (a response, an
event set by the service, a line printed by a child process), never on a sleep.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import socket
from collections.abc import Callable

import pytest
from support import KB_FILES, ServerProcess, free_udp_port

from coapkb.transport import open_client, serve, transport_for
from coapkb.transport.base import Endpoint, PeerUnreachable, ResourceInfo, Service, TransportError
from coapkb.transport.dds.config import client_domain_xml, server_domain_xml, topic_names
from coapkb.transport.dds.envelope import Envelope
from coapkb.transport.dds.transport import DdsClientTransport, DdsOptions, DdsServerTransport
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status
from coapkb.wire.codec import decode_cbor

LOCAL = Endpoint("dds", "127.0.0.1", 0)


class DemoService(Service):
    """Echo, error, crash, slow and an observable counter."""

    def __init__(self) -> None:
        self.counter = 0
        self.seen: list[Request] = []
        self._subscribers: dict[int, Callable[[], None]] = {}
        self._next_sub = 0
        self.unsubscribed = asyncio.Event()
        self.handling = asyncio.Event()

    def resources(self) -> list[ResourceInfo]:
        return [ResourceInfo("/echo"), ResourceInfo("/counter", obs=True)]

    async def handle(self, request: Request) -> Response:
        self.seen.append(request)
        self.handling.set()
        if request.path == "/echo":
            described = {
                "method": str(request.method),
                "path": request.path,
                "query": dict(request.query),
                "content_format": request.content_format,
                "accept": request.accept,
                "etags": [e.hex() for e in request.etags],
            }
            return Response(
                Status.CONTENT,
                json.dumps(described).encode() + b"\n" + request.payload,
                content_format=ContentFormat.JSON,
                max_age=42,
                etag=b"\x01\x02\x03\x04",
            )
        if request.path == "/crash":
            raise RuntimeError("a buggy service")
        if request.path == "/slow":
            await asyncio.sleep(float(request.query.get("delay", "0")))  # simulated work
            return Response(Status.CONTENT, request.payload)
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

    @property
    def subscriber_count(self) -> int:
        return len(self._subscribers)

    def bump(self) -> None:
        self.counter += 1
        for on_change in list(self._subscribers.values()):
            on_change()


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


async def test_round_trip_all_fields(server, client, service) -> None:
    request = Request(
        Method.POST, "/echo", {"a": "1", "b": "two"}, b"payload", ContentFormat.CBOR, ContentFormat.JSON,
        etags=(b"\x09\x08",),
    )
    response = await client.request(server.endpoint, request, timeout=10)
    assert response.status is Status.CONTENT
    head, _, body = response.payload.partition(b"\n")
    assert json.loads(head) == {
        "method": "POST", "path": "/echo", "query": {"a": "1", "b": "two"},
        "content_format": ContentFormat.CBOR, "accept": ContentFormat.JSON, "etags": ["0908"],
    }
    assert body == b"payload"
    assert (response.content_format, response.max_age, response.etag) == (ContentFormat.JSON, 42, b"\x01\x02\x03\x04")
    assert service.seen[0].peer is None
    assert client.counters.messages_sent == 1 and client.counters.messages_received == 1
    assert server.counters.bytes_received == client.counters.bytes_sent > len(b"payload")
    assert server.counters.bytes_sent == client.counters.bytes_received


async def test_error_status_unknown_path_and_crashing_handler(server, client) -> None:
    missing = await client.request(server.endpoint, Request(Method.GET, "/nope"), timeout=10)
    assert missing.status is Status.NOT_FOUND
    crashed = await client.request(server.endpoint, Request(Method.GET, "/crash"), timeout=10)
    assert crashed.status is Status.INTERNAL_SERVER_ERROR


async def test_concurrent_requests_get_their_own_answers(server, client) -> None:
    payloads = [f"n{i}".encode() for i in range(40)]
    answers = await asyncio.gather(*(
        client.request(server.endpoint, Request(Method.POST, "/slow", payload=p), timeout=10) for p in payloads
    ))
    assert [a.payload for a in answers] == payloads


async def test_large_payload_is_fragmented_and_reassembled(server, client) -> None:
    blob = os.urandom(20_000)  # well above one datagram (MaxMessageSize)
    response = await client.request(server.endpoint, Request(Method.POST, "/slow", payload=blob), timeout=10)
    assert response.payload == blob


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


async def test_slow_peer_times_out_then_serves_again(server, client) -> None:
    await client.request(server.endpoint, Request(Method.GET, "/echo"), timeout=10)
    with pytest.raises(PeerUnreachable, match="no answer .* within 0.3s"):
        await client.request(server.endpoint, Request(Method.GET, "/slow", query={"delay": "2"}), timeout=0.3)
    ok = await client.request(server.endpoint, Request(Method.GET, "/echo"), timeout=5)
    assert ok.status is Status.CONTENT


async def test_closed_client_refuses_and_pending_request_fails(server, service) -> None:
    cli = DdsClientTransport()
    pending = asyncio.create_task(
        cli.request(server.endpoint, Request(Method.GET, "/slow", query={"delay": "3"}), timeout=10)
    )
    await asyncio.wait_for(service.handling.wait(), 10)
    await cli.aclose()
    with pytest.raises(TransportError):
        await asyncio.wait_for(pending, 6)
    with pytest.raises(TransportError, match="closed"):
        await cli.request(server.endpoint, Request(Method.GET, "/echo"), timeout=1)


async def test_port_in_use_is_a_transport_error(server, service) -> None:
    with pytest.raises(TransportError, match="cannot serve"):
        await DdsServerTransport.start(service, server.endpoint)


# =========================================================================== bad input


async def test_garbage_datagrams_and_samples_do_not_kill_the_server(server, client, caplog) -> None:
    await client.request(server.endpoint, Request(Method.GET, "/echo"), timeout=10)
    # Raw datagrams to the participant's one port: not RTPS, an RTPS header
    # with junk after it, a truncated header.  Cyclone drops them.
    junk = [b"", b"\x00" * 3, os.urandom(200), b"RTPS\x02\x01\x01\x10" + os.urandom(12) + os.urandom(64), b"RTPS"]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for datagram in junk * 5:
            s.sendto(datagram, (server.endpoint.host, server.endpoint.port))
    # Well-formed DDS samples whose envelope is not a coapkb request: counted, dropped.
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


async def test_observe_initial_value_updates_then_deregisters(server, client, service) -> None:
    values: list[bytes] = []
    async with contextlib.aclosing(client.observe(server.endpoint, Request(Method.GET, "/counter"))) as updates:
        async for response in updates:
            values.append(response.payload)
            if len(values) == 4:
                break
            service.bump()
    assert values == [b"0", b"1", b"2", b"3"]
    await asyncio.wait_for(service.unsubscribed.wait(), 10)
    assert service.subscriber_count == 0
    assert server.observation_count == 0


async def test_observe_error_is_one_item(server, client) -> None:
    items = [r async for r in client.observe(server.endpoint, Request(Method.GET, "/nope"))]
    assert [r.status for r in items] == [Status.NOT_FOUND]
    assert server.observation_count == 0


async def test_observe_dead_peer(client) -> None:
    peer = Endpoint("dds", "127.0.0.1", free_udp_port())
    with pytest.raises(PeerUnreachable):
        async for _ in client.observe(peer, Request(Method.GET, "/counter"), timeout=1):
            pass


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
    peer = Endpoint.parse(robot.uri)
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
