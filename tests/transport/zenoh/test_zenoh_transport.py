"""Zenoh transport: client and server on real TCP (and UDP) sockets on 127.0.0.1,
in this process and against a real ``coapkb serve`` process.

What every transport does (requests, observe, dead peers, garbage at the
port, security, ...) is tests/transport/test_contract.py; here is what only
Zenoh has: its key mapping, its queries' parser, session loss, a robot process.

Every test that waits for something waits on the thing itself (a response, an
event set by the service, a line printed by a child process), never on a sleep.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable

import cbor2
import pytest
import zenoh
from support import KB_FILES, ServerProcess, free_tcp_port

from coapkb.transport import open_client, serve
from coapkb.transport.base import Endpoint, PeerUnreachable, ResourceInfo, Service, TransportError
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status
from coapkb.transport.registry import parse_endpoint
from coapkb.transport.zenoh.mapping import KEY_ROOT
from coapkb.transport.zenoh.transport import (
    ZenohClientTransport,
    ZenohOptions,
    ZenohServerTransport,
    session_config,
)
from coapkb.wire.codec import decode_cbor

LOCAL = Endpoint("zenoh", "127.0.0.1", 0)


class DemoService(Service):
    """Echo and an observable counter (what the transport contract,
    tests/transport/test_contract.py, does not cover is Zenoh's own)."""

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

    def bump(self) -> None:
        self.counter += 1
        for on_change in list(self._subscribers.values()):
            on_change()


@pytest.fixture
def service() -> DemoService:
    return DemoService()


@pytest.fixture
async def server(service: DemoService):
    srv = await ZenohServerTransport.start(service, LOCAL)
    yield srv
    await srv.aclose()


@pytest.fixture
async def client():
    cli = ZenohClientTransport()
    yield cli
    await cli.aclose()


# =========================================================================== request / response


async def test_path_without_a_key_is_a_transport_error(server, client) -> None:
    with pytest.raises(TransportError, match="empty segment"):
        await client.request(server.endpoint, Request(Method.GET, "/kb//x"), timeout=1)


async def test_garbage_gets_an_error_reply_and_the_server_lives(server, client, caplog) -> None:
    """Queries from a raw Zenoh session that are not coapkb requests."""
    raw = zenoh.open(session_config("client", connect=(f"tcp/{server.endpoint.hostport}",)))
    garbage = [
        (f"{KEY_ROOT}/echo", b"\xff"),  # not CBOR
        (f"{KEY_ROOT}/echo", cbor2.dumps({"m": 1})),  # not an array
        (f"{KEY_ROOT}/echo", cbor2.dumps([99])),  # unknown method
        (f"{KEY_ROOT}/echo", cbor2.dumps([1, "x"])),  # accept not a uint
        (f"{KEY_ROOT}/echo", cbor2.dumps([1, None, [], 0])),  # observe without a notification key
        (f"{KEY_ROOT}/echo", cbor2.dumps([1, None, [], 0, "elsewhere/x"])),  # ... or a foreign one
        (f"{KEY_ROOT}/echo", cbor2.dumps([1, None, [b""]])),  # empty etag
        (f"{KEY_ROOT}/echo", cbor2.dumps([1] * 6)),  # too long
        (f"{KEY_ROOT}/%FF", None),  # key not UTF-8 once decoded
    ]
    try:
        with caplog.at_level(logging.WARNING, logger="coapkb.transport.zenoh.transport"):
            for _ in range(5):
                for key, attachment in garbage:
                    replies = await asyncio.to_thread(lambda key=key, attachment=attachment: list(raw.get(key, attachment=attachment, timeout=2)))
                    assert len(replies) == 1 and replies[0].err is not None, [(r.err.payload.to_bytes() if r.err else r.ok) for r in replies]
                    assert replies[0].err.payload.to_bytes().startswith(b"4.00")
        assert server.malformed == 5 * len(garbage)
        assert len([r for r in caplog.records if "malformed" in r.getMessage()]) == 1, "rate-limited"
    finally:
        raw.close()
    ok = await client.request(server.endpoint, Request(Method.GET, "/echo"), timeout=2)
    assert ok.status is Status.CONTENT


# =========================================================================== observe


async def test_observer_whose_session_closes_is_forgotten(server, service) -> None:
    cli = ZenohClientTransport()
    updates = cli.observe(server.endpoint, Request(Method.GET, "/counter"))
    assert (await anext(updates)).payload == b"0"
    assert server.observation_count == 1
    await cli.aclose()  # no deregistration: the session just goes away
    await asyncio.wait_for(service.unsubscribed.wait(), 5)  # the server saw its subscriber go
    assert server.observation_count == 0
    await updates.aclose()


async def test_observe_cap(service, client) -> None:
    async with await ZenohServerTransport.start(service, LOCAL, options=ZenohOptions(max_observations=1)) as srv:
        first = client.observe(srv.endpoint, Request(Method.GET, "/counter"))
        await anext(first)
        extra = [r async for r in client.observe(srv.endpoint, Request(Method.GET, "/counter"))]
        assert [r.payload for r in extra] == [b"0"]  # answered, not registered: the iterator ends
        await first.aclose()


# =========================================================================== a real robot process


async def test_named_query_to_a_serve_process_and_its_restart() -> None:
    port = free_tcp_port()
    args = ("--kb", *KB_FILES, "--bind", f"127.0.0.1:{port}", "--transport", "zenoh")
    robot = await ServerProcess.start(*args)
    peer = parse_endpoint(robot.uri)
    assert peer == Endpoint("zenoh", "127.0.0.1", port)
    client = await open_client("zenoh")
    try:
        named = Request(Method.GET, "/kb/q/object-location", {"name": "Gucci_bag_14"}, accept=ContentFormat.CBOR)
        response = await client.request(peer, named, timeout=10)
        assert response.status is Status.CONTENT and response.content_format == ContentFormat.CBOR
        rows = decode_cbor(response.payload).rows
        assert len(rows) == 1
        missing = await client.request(peer, Request(Method.GET, "/kb/q/no-such-query"), timeout=5)
        assert missing.status is Status.NOT_FOUND
        await robot.stop()
        with pytest.raises(PeerUnreachable):
            await client.request(peer, named, timeout=0.5)
        robot = await ServerProcess.start(*args)  # back on its port: the client session reconnects
        again = await client.request(peer, named, timeout=10)
        assert again.payload == response.payload
    finally:
        await client.aclose()
        await robot.stop()


async def test_serve_factory_picks_zenoh(service) -> None:
    srv = await serve(service, Endpoint("zenoh", "127.0.0.1", 0))
    try:
        assert isinstance(srv, ZenohServerTransport)
    finally:
        await srv.aclose()


async def test_observe_again_after_the_peer_restarts(service, client) -> None:
    """The first observation's session lost its peer; the next observation
    reaches the restarted peer at once: on a fresh session, or on the old
    one when Zenoh's own reconnect got there first (a race the test does
    not decide, so it does not check which)."""
    srv = await ZenohServerTransport.start(service, LOCAL)
    peer = srv.endpoint
    updates = client.observe(peer, Request(Method.GET, "/counter"))
    assert (await anext(updates)).payload == b"0"
    await updates.aclose()
    await srv.aclose()
    service.bump()
    async with await ZenohServerTransport.start(service, peer):
        again = client.observe(peer, Request(Method.GET, "/counter"), timeout=5)
        assert (await anext(again)).payload == b"1"
        service.bump()
        assert (await anext(again)).payload == b"2"
        await again.aclose()
