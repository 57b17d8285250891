"""ZeroMQ transport: wire codec, client and server on real TCP sockets on 127.0.0.1.

What every transport does (requests, observe, dead peers, garbage at the
port, security, ...) is tests/transport/test_contract.py; here is what only
ZeroMQ has: its envelope and parser, its options, IPv6, a server process.

Every test that waits for something waits on the thing itself (a response, an
event set by the service, a line printed by a child process), never on a sleep.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import sys
import textwrap

import cbor2
import pytest
import zmq
import zmq.asyncio
from hypothesis import given, settings
from hypothesis import strategies as st
from support import require

from coapkb.transport.base import (
    Endpoint,
    PeerUnreachable,
    ResourceInfo,
    Service,
)
from coapkb.transport.envelope import (
    Observe,
    WireError,
    decode_request,
    decode_response,
    encode_request,
    encode_response,
)
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status
from coapkb.transport.zmq.transport import ZmqClientTransport, ZmqOptions, ZmqServerTransport, zmtp_frame_bytes

LOCAL = Endpoint("zmq", "127.0.0.1", 0)


class DemoService(Service):
    """Echo, an error and an observable value (what the transport contract,
    tests/transport/test_contract.py, does not cover is ZeroMQ's own)."""

    def __init__(self) -> None:
        self.seen: list[Request] = []

    def resources(self) -> list[ResourceInfo]:
        return [ResourceInfo("/echo", methods=("GET", "POST")), ResourceInfo("/error"),
                ResourceInfo("/counter", obs=True)]

    async def handle(self, request: Request) -> Response:
        self.seen.append(request)
        if request.path == "/echo":
            return Response(Status.CONTENT, b"echo:" + request.payload)
        if request.path == "/error":
            return Response.error(Status.BAD_REQUEST, "bad query")
        if request.path == "/counter":
            return Response(Status.CONTENT, b"0", ContentFormat.TEXT)
        return Response.error(Status.NOT_FOUND, f"no resource {request.path}")


@pytest.fixture
def service() -> DemoService:
    return DemoService()


@pytest.fixture
async def server(service: DemoService):
    srv = await ZmqServerTransport.start(service, LOCAL)
    yield srv
    await srv.aclose()


@pytest.fixture
async def client():
    cli = ZmqClientTransport()
    yield cli
    await cli.aclose()


# =========================================================================== client/server


async def test_garbage_does_not_kill_the_server(server, client, caplog) -> None:
    garbage: list[list[bytes]] = [
        [b""],
        [b"\xff"],
        [b"\x9f" * 1000],  # deeply nested indefinite arrays
        [b"hello world"],
        [cbor2.dumps({"token": 1})],
        [cbor2.dumps([1, 2, 3])],
        [cbor2.dumps([1, 99, "/echo", {}, None, None, b""])],  # unknown method
        [cbor2.dumps([1, 1, "/echo", {"a": 1}, None, None, b""])],  # bad query
        [cbor2.dumps([-1, 1, "/echo", {}, None, None, b""])],  # negative token
        [cbor2.dumps([1, 1, "/echo", {}, None, None, b""]) + b"\x00"],  # trailing byte
        [b"two", b"frames"],
        [bytes(range(256)) * 10],
    ]
    ctx = zmq.asyncio.Context()
    raw = ctx.socket(zmq.DEALER)
    raw.setsockopt(zmq.LINGER, 0)
    raw.connect(f"tcp://{server.endpoint.hostport}")
    try:
        with caplog.at_level(logging.WARNING, logger="coapkb.transport.zmq.transport"):
            for _ in range(20):
                for frames in garbage:
                    await raw.send_multipart(frames)
            # A good request on the same connection is answered after the garbage.
            await raw.send(encode_request(Request(Method.GET, "/echo", payload=b"ok"), token=7))
            token, response, seq = decode_response(await asyncio.wait_for(raw.recv(), 5))
        assert (token, seq) == (7, None)
        assert response.payload.endswith(b"ok")
        assert server.malformed == 20 * len(garbage)
        warnings = [r for r in caplog.records if "malformed" in r.getMessage()]
        assert len(warnings) == 1, "the garbage flood must be rate-limited in the log"
    finally:
        raw.close(linger=0)
        ctx.term()
    ok = await client.request(server.endpoint, Request(Method.GET, "/echo"), timeout=2)
    assert ok.status is Status.CONTENT


async def test_oversized_request_drops_only_that_connection(service, client) -> None:
    async with await ZmqServerTransport.start(service, LOCAL, options=ZmqOptions(max_request_bytes=10_000)) as srv:
        ctx = zmq.asyncio.Context()
        raw = ctx.socket(zmq.DEALER)
        raw.setsockopt(zmq.LINGER, 0)
        raw.connect(f"tcp://{srv.endpoint.hostport}")
        try:
            await raw.send(encode_request(Request(Method.POST, "/echo", payload=bytes(20_000)), token=1))
            ok = await client.request(srv.endpoint, Request(Method.GET, "/echo", payload=b"small"), timeout=2)
            assert ok.payload.endswith(b"small")
            assert [r.payload for r in service.seen] == [b"small"]
        finally:
            raw.close(linger=0)
            ctx.term()


def _has_ipv6_loopback() -> bool:
    try:
        with socket.socket(socket.AF_INET6) as s:
            s.bind(("::1", 0))
        return True
    except OSError:
        return False


async def test_ipv6_endpoint(service, client) -> None:
    require(_has_ipv6_loopback(), "no IPv6 loopback")
    async with await ZmqServerTransport.start(service, Endpoint("zmq", "::1", 0)) as srv:
        assert str(srv.endpoint).startswith("zmq://[::1]:")
        ok = await client.request(srv.endpoint, Request(Method.GET, "/echo", payload=b"v6"), timeout=2)
        assert ok.payload.endswith(b"v6")


async def test_counters_count_both_directions(server, client) -> None:
    request = Request(Method.GET, "/echo", payload=b"x" * 300)
    response = await client.request(server.endpoint, request, timeout=2)
    await client.request(server.endpoint, Request(Method.GET, "/error"), timeout=2)
    c, s = client.counters, server.counters
    assert c.messages_sent == s.messages_received == 2
    assert c.messages_received == s.messages_sent == 2
    assert c.bytes_sent == s.bytes_received
    assert c.bytes_received == s.bytes_sent
    # envelope + ZMTP frame header: a 300-byte payload needs the 8-byte length form
    assert c.bytes_sent >= zmtp_frame_bytes(len(encode_request(request, token=0)))
    assert c.bytes_received > len(response.payload)
    assert c.retransmissions == 0


# =========================================================================== observe


async def test_observe_cap_per_client(service) -> None:
    async with (
        await ZmqServerTransport.start(service, LOCAL, options=ZmqOptions(max_observations=1)) as srv,
        ZmqClientTransport() as cli,
    ):
        req = Request(Method.GET, "/counter")
        async with contextlib.aclosing(cli.observe(srv.endpoint, req)) as first:
            assert (await anext(first)).payload == b"0"
            # No slot left: the answer comes, but the iteration ends (not registered).
            assert [r.payload async for r in cli.observe(srv.endpoint, req)] == [b"0"]
            assert srv.observation_count == 1


# =========================================================================== separate process

SERVER_PROCESS = textwrap.dedent(
    """
    import asyncio, sys
    from coapkb.transport.messages import Response, Status
    from coapkb.transport.base import Endpoint, Service
    from coapkb.transport.zmq.transport import ZmqServerTransport

    class Echo(Service):
        def resources(self):
            return []
        async def handle(self, request):
            return Response(Status.CONTENT, b"pong:" + request.payload)

    async def main():
        port = int(sys.argv[1])
        server = await ZmqServerTransport.start(Echo(), Endpoint("zmq", "127.0.0.1", port))
        print("READY", server.endpoint.port, flush=True)
        await asyncio.to_thread(sys.stdin.read)  # serve until the parent closes our stdin
        await server.aclose()

    asyncio.run(main())
    """
)


async def spawn_server(port: int = 0) -> tuple[asyncio.subprocess.Process, Endpoint]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-c",
        SERVER_PROCESS,
        str(port),
        stdin=asyncio.subprocess.PIPE,
        stdout=asyncio.subprocess.PIPE,
    )
    assert proc.stdout is not None
    line = await asyncio.wait_for(proc.stdout.readline(), 30)
    word, _, real_port = line.decode().partition(" ")
    if word != "READY":
        proc.kill()
        await proc.wait()
        raise AssertionError(f"server process did not start: {line!r}")
    return proc, Endpoint("zmq", "127.0.0.1", int(real_port))


async def stop_server(proc: asyncio.subprocess.Process) -> None:
    assert proc.stdin is not None
    proc.stdin.close()
    try:
        assert await asyncio.wait_for(proc.wait(), 10) == 0
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


async def test_server_in_another_process_survives_restart(client) -> None:
    proc, peer = await spawn_server()
    try:
        response = await client.request(peer, Request(Method.GET, "/ping", payload=b"1"), timeout=5)
        assert response.payload == b"pong:1"
    finally:
        await stop_server(proc)
    with pytest.raises(PeerUnreachable):
        await client.request(peer, Request(Method.GET, "/ping", payload=b"2"), timeout=0.3)
    proc, peer2 = await spawn_server(peer.port)  # the robot comes back on its port
    try:
        assert peer2 == peer
        response = await client.request(peer, Request(Method.GET, "/ping", payload=b"3"), timeout=5)
        assert response.payload == b"pong:3"
    finally:
        await stop_server(proc)


async def test_reconnects_without_a_timeout_in_between(client) -> None:
    """The DEALER reconnects by itself (100 ms, backing off to 2 s)."""
    proc, peer = await spawn_server()
    try:
        assert (await client.request(peer, Request(Method.GET, "/", payload=b"a"), timeout=5)).payload == b"pong:a"
    finally:
        await stop_server(proc)
    proc, _ = await spawn_server(peer.port)
    try:
        assert (await client.request(peer, Request(Method.GET, "/", payload=b"b"), timeout=5)).payload == b"pong:b"
    finally:
        await stop_server(proc)


# =========================================================================== wire codec

_uint = st.integers(min_value=0, max_value=2**64 - 1)
_opt_uint = st.none() | st.integers(min_value=0, max_value=2**32)
requests = st.builds(
    Request,
    method=st.sampled_from(list(Method)),
    path=st.text(max_size=40),
    query=st.dictionaries(st.text(max_size=10), st.text(max_size=10), max_size=4),
    payload=st.binary(max_size=300),
    content_format=_opt_uint,
    accept=_opt_uint,
)
responses = st.builds(
    Response,
    status=st.sampled_from(list(Status)),
    payload=st.binary(max_size=300),
    content_format=_opt_uint,
    max_age=_opt_uint,
    etag=st.none() | st.binary(min_size=1, max_size=8),
)
cbor_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**70), 2**70)
    | st.text(max_size=8)
    | st.binary(max_size=8)
    | st.floats(allow_nan=False),
    lambda children: st.lists(children, max_size=9) | st.dictionaries(st.text(max_size=4), children, max_size=3),
    max_leaves=20,
)


@given(requests, _uint, st.sampled_from(list(Observe)))
def test_request_codec_round_trip(request: Request, token: int, observe: Observe) -> None:
    assert decode_request(encode_request(request, token=token, observe=observe)) == (token, request, observe)


@given(responses, _uint, st.none() | _uint)
def test_response_codec_round_trip(response: Response, token: int, seq: int | None) -> None:
    assert decode_response(encode_response(token, response, seq=seq)) == (token, response, seq)


def test_observe_flag_is_bool_compatible() -> None:
    data = encode_request(Request(Method.GET, "/counter"), token=3, observe=True)
    assert decode_request(data)[2] == True  # noqa: E712 - the flag compares equal to True, as a bool does
    assert not decode_request(encode_request(Request(Method.GET, "/counter"), token=3))[2]


def test_envelope_is_compact() -> None:
    assert len(encode_request(Request(Method.GET, "/x"), token=1)) == 10
    assert len(encode_response(1, Response(Status.CONTENT))) == 8


@settings(max_examples=500)
@given(st.binary(max_size=200))
def test_fuzz_bytes_only_wire_error(data: bytes) -> None:
    for decode in (decode_request, decode_response):
        with contextlib.suppress(WireError):
            decode(data)


@settings(max_examples=500)
@given(cbor_values)
def test_fuzz_cbor_structures_only_wire_error(value: object) -> None:
    data = cbor2.dumps(value)
    for decode in (decode_request, decode_response):
        with contextlib.suppress(WireError):
            decode(data)


@given(requests, _uint, st.data())
def test_fuzz_mutated_requests_only_wire_error(request: Request, token: int, data: st.DataObject) -> None:
    encoded = bytearray(encode_request(request, token=token))
    i = data.draw(st.integers(0, len(encoded) - 1))
    encoded[i] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(encoded)))
    with contextlib.suppress(WireError):
        decode_request(bytes(encoded[:cut]))


def test_wire_error_messages_are_clear() -> None:
    with pytest.raises(WireError, match="not CBOR"):
        decode_request(b"\xff")
    with pytest.raises(WireError, match="trailing"):
        decode_request(encode_request(Request(Method.GET, "/"), token=1) + b"\x00")
    with pytest.raises(WireError, match="unknown method"):
        decode_request(cbor2.dumps([1, 9, "/", {}, None, None, b""]))
    with pytest.raises(WireError, match="unknown status"):
        decode_response(cbor2.dumps([1, 299, None, None, None, b""]))
    with pytest.raises(WireError, match="array of 6 or 7"):
        decode_response(cbor2.dumps([1]))
    assert issubclass(WireError, ValueError)


def test_encode_rejects_what_the_envelope_cannot_carry() -> None:
    with pytest.raises(ValueError):
        encode_request(Request(Method.GET, "/"), token=-1)
    with pytest.raises(ValueError):
        encode_request(Request(Method.GET, "/", content_format=-5), token=1)
    with pytest.raises(ValueError):
        encode_response(1, Response(Status.CONTENT), seq=-1)


def test_wire_carries_etags_with_and_without_observe() -> None:
    from coapkb.transport.envelope import Observe, decode_request, encode_request

    request = Request(Method.GET, "/kb/q/x", {"name": "y"}, accept=60, etags=(b"\x01\x02", b"abcdefgh"))
    for observe in (Observe.NONE, Observe.REGISTER):
        token, decoded, obs = decode_request(encode_request(request, observe=observe, token=7))
        assert (token, decoded, obs) == (7, request, observe)
