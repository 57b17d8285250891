"""The transport contract: what every registered transport does, on real
sockets on 127.0.0.1.

Every case runs once per entry of :data:`coapkb.transport.registry.REGISTERED`
(a transport registered later is tested without a change here), through the
registry's own ``open_client`` and ``serve`` factories, against one
:class:`ContractService`.  A case that cannot apply to a transport (security
on one that cannot be secured) is skipped through :func:`support.not_applicable`
with the registry's reason; that skip stays a skip in CI.

What stays in the per-transport files is what only that transport has: its
wire format and parser, its options and socket tuning, its discovery, Block-wise
and QUIC, interop with other implementations, a real ``coapkb serve`` process.

Cases that leave nothing behind share one server and client per transport
(:func:`pair`): a DDS pair's first answer alone takes up to two of Cyclone's
1 s heartbeats.  The others get their own.

Every wait is on the thing itself (an answer, an exception, the server's
observation count), never a sleep; ``/slow``'s delay is the service's
simulated work, so that answers come back out of order.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import json
import random
import socket
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from support import not_applicable, observation_count, until

from coapkb.security import generate_team, load_identity
from coapkb.security.keys import default_members
from coapkb.security.mechanisms import client_security, server_security
from coapkb.transport import open_client, serve
from coapkb.transport.base import (
    ClientTransport,
    Endpoint,
    PeerTimeout,
    PeerUnreachable,
    ResourceInfo,
    ServerTransport,
    Service,
    TransportError,
)
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status
from coapkb.transport.registry import REGISTERED, TransportInfo

pytestmark = pytest.mark.asyncio(loop_scope="module")

HOST = "127.0.0.1"
#: Long enough for any answer on loopback on a loaded machine; a case that
#: waits this long has failed.
ANSWER_S = 10.0
#: The time budget of a request that must fail.
SHORT_S = 0.3
#: How much later than its budget a failing request may end (a loaded machine).
LATE_S = 3.0
#: The budget of a stranger's request to a secured server: long enough for
#: an answer refusing it (CoAP's 4.01), if the transport gives one.
STRANGER_S = 0.5
#: How long a server may take to drop an observation that was closed.
FORGET_S = 2.0
#: A large body: many CoAP blocks, many DDS fragments, many TCP segments;
#: under the ZeroMQ server's 1 MiB request limit.
LARGE = bytes(range(256)) * 2000  # 512 kB
#: Over the largest request some transports take: the ZeroMQ server's 1 MiB
#: (``max_request_bytes``), the CoAP server's Block1 spool (1 MiB).
HUGE = bytes(range(256)) * 6144  # 1.5 MiB
#: The refusal :meth:`ContractService.admit` answers with, to be seen unchanged.
REFUSAL = Response(Status.FORBIDDEN, b"not for you", ContentFormat.TEXT, max_age=7, etag=b"\x0a\x0b")
#: How long closing a client may take.
CLOSE_S = 2.0

#: Bugs this suite found, by case and scheme: the case is expected to fail
#: there (strictly: once the bug is fixed it passes, and its entry must go).
#: ``pytest --runxfail`` shows the failures.
KNOWN_BUGS: dict[str, dict[str, str]] = {
    "test_closing_the_iterator_deregisters": {
        "coap": "closing the CoAP observe iterator sends no deregistration: the server keeps the observation "
                "(and its slot) until a notification after it is refused, the first one still sent and acknowledged",
    },
    "test_a_closed_observation_frees_its_slot": {
        "coap": "closed CoAP observations keep the resource's OBSERVERS_MAX slots: past 64, observers are refused",
    },
}
#: Known bugs whose failing run takes long: not run unless asked (``--runxfail``).
SLOW_TO_FAIL: set[str] = set()


@pytest.fixture(autouse=True)
def _known_bug(request: pytest.FixtureRequest) -> None:
    callspec = getattr(request.node, "callspec", None)
    transport = callspec.params.get("transport") if callspec is not None else None
    why = KNOWN_BUGS.get(request.node.originalname, {}).get(getattr(transport, "scheme", ""))
    if why is not None:
        run = request.node.originalname not in SLOW_TO_FAIL or request.config.option.runxfail
        request.applymarker(pytest.mark.xfail(reason=f"bug: {why}", strict=True, run=run))


class ContractService(Service):
    """Echo, mirror, chosen status, error, crash, slow, held, large and an
    observable counter; records every request and every ``admit`` question."""

    def __init__(self) -> None:
        self.counter = 0
        #: /counter answers 4.04 from now on.
        self.broken = False
        self.seen: list[Request] = []
        self.asked: list[tuple[str | None, str, str]] = []
        #: Paths ``admit`` refuses with :data:`REFUSAL`.
        self.refused: set[str] = set()
        self.handling = asyncio.Event()  # a request reached handle()
        self._release = asyncio.Event()  # answers /hold, at last
        self._subscribers: dict[int, Callable[[], None]] = {}
        self._next_sub = 0

    def reset(self) -> None:
        """Forget the requests seen and the refusals; let what was held go."""
        self.counter, self.broken = 0, False
        self.seen.clear()
        self.asked.clear()
        self.refused.clear()
        self.handling.clear()
        self._release.set()
        self._release = asyncio.Event()

    def resources(self) -> list[ResourceInfo]:
        return [
            ResourceInfo("/echo", methods=("GET", "POST", "FETCH", "PUT", "DELETE", "PATCH", "iPATCH")),
            ResourceInfo("/mirror", methods=("POST", "FETCH")),
            ResourceInfo("/status"),
            ResourceInfo("/error"),
            ResourceInfo("/crash"),
            ResourceInfo("/slow", methods=("GET", "POST")),
            ResourceInfo("/hold"),
            ResourceInfo("/large"),
            ResourceInfo("/counter", obs=True),
            ResourceInfo("/guarded", obs=True, methods=("GET", "POST")),
        ]

    def admit(self, sender: str | None, method: str, path: str) -> Response | None:
        self.asked.append((sender, method, path))
        return REFUSAL if path in self.refused else None

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
            return Response(Status.CONTENT, json.dumps(described).encode() + b"\n" + request.payload,
                            content_format=ContentFormat.JSON, max_age=42, etag=b"\x01\x02\x03\x04")
        if request.path == "/mirror":
            return Response(Status.CHANGED if request.method == Method.POST else Status.CONTENT, request.payload,
                            content_format=request.content_format)
        if request.path == "/status":
            status = Status(int(request.query["code"]))
            return Response(status, b"" if status == Status.VALID else f"status {status.dotted}".encode(),
                            ContentFormat.TEXT if status != Status.VALID else None, max_age=3, etag=b"\x05")
        if request.path == "/error":
            return Response.error(Status.BAD_REQUEST, "bad query")
        if request.path == "/crash":
            raise RuntimeError("a buggy service")
        if request.path == "/slow":
            await asyncio.sleep(float(request.query.get("delay", "0")))  # simulated work
            return Response(Status.CONTENT, request.payload)
        if request.path == "/hold":
            await self._release.wait()  # not in the client's budget
            return Response(Status.CONTENT, b"too late")
        if request.path == "/large":
            return Response(Status.CONTENT, LARGE, ContentFormat.CBOR)
        if request.path in ("/counter", "/guarded") and not self.broken:
            return Response(Status.CONTENT, str(self.counter).encode(), ContentFormat.TEXT)
        return Response.error(Status.NOT_FOUND, f"no resource {request.path}")

    def subscribe(self, path: str, on_change: Callable[[], None]) -> Callable[[], None]:
        key = self._next_sub = self._next_sub + 1
        self._subscribers[key] = on_change
        return lambda: self._subscribers.pop(key, None)

    def bump(self) -> None:
        self.counter += 1
        for on_change in list(self._subscribers.values()):
            on_change()


# --------------------------------------------------------------------------- helpers


def local(transport: TransportInfo, port: int = 0) -> Endpoint:
    return Endpoint(transport.scheme, HOST, port)


def unused_port(transport: TransportInfo) -> int:
    """A port nobody listens on, of the kind the transport listens on."""
    kind = socket.SOCK_DGRAM if transport.datagram else socket.SOCK_STREAM
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind((HOST, 0))
        return int(s.getsockname()[1])


async def start(transport: TransportInfo, service: Service, port: int = 0) -> ServerTransport:
    return await transport.serve(service, local(transport, port), None, None, {})


async def open_for_dead_peers(transport: TransportInfo) -> ClientTransport:
    """The registry's client, for cases that ask dead peers.  Zenoh's gets a
    short session-open timeout: its ``aclose`` waits for a session still
    opening, which to a dead QUIC peer takes Zenoh's 10 s (a bug:
    :func:`test_a_client_closes_promptly_after_an_unreachable_peer`, which
    uses the registry's own)."""
    table = {"open_timeout_s": 0.3} if transport.scheme.startswith("zenoh") else {}
    return await transport.open_client(None, None, table)


def observe(client: ClientTransport, peer: Endpoint, request: Request,
            timeout: float | None = None) -> AsyncIterator[Response]:
    """``client.observe``, with a budget for the first answer where the
    transport takes one (the interface's ``observe`` has none)."""
    if timeout is not None and "timeout" in inspect.signature(client.observe).parameters:
        return client.observe(peer, request, timeout=timeout)  # type: ignore[call-arg]
    return client.observe(peer, request)


def distinct(items: list[Any]) -> list[Any]:
    """``items`` without repeats, in order: a transport may deliver a request
    twice (CoAP's retry is a new exchange: requests must be idempotent)."""
    out: list[Any] = []
    for item in items:
        if item not in out:
            out.append(item)
    return out


async def unreachable(client: ClientTransport, peer: Endpoint, request: Request, *,
                      timeout: float = SHORT_S) -> PeerUnreachable:
    """``request`` to ``peer`` fails with PeerUnreachable (or its subclass
    PeerTimeout), at the latest a little after ``timeout``: never a hang,
    never another exception; its message, one line, names the peer."""
    budget = asyncio.timeout(timeout + LATE_S)
    try:
        async with budget:
            with pytest.raises(PeerUnreachable) as caught:
                await client.request(peer, request, timeout=timeout)
    except TimeoutError:
        if not budget.expired():
            raise  # a TimeoutError of the transport's own: not the contract's exception
        raise AssertionError(f"request to {peer} still pending {timeout + LATE_S:g}s into a {timeout:g}s budget") from None
    message = str(caught.value)
    assert str(peer) in message and "\n" not in message, message
    return caught.value


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module", params=REGISTERED, ids=lambda t: t.scheme)
def transport(request: pytest.FixtureRequest) -> TransportInfo:
    info: TransportInfo = request.param
    return info


@dataclass(frozen=True)
class Pair:
    """A server of a :class:`ContractService` and a client of it."""

    server: ServerTransport
    client: ClientTransport
    service: ContractService


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def standing(transport: TransportInfo) -> AsyncIterator[Pair]:
    service = ContractService()
    server = await start(transport, service)
    client = await transport.open_client(None, None, {})
    yield Pair(server, client, service)
    await client.aclose()
    await server.aclose()


@pytest.fixture
def pair(standing: Pair) -> Pair:
    """The transport's standing pair, its service as new: for a case that
    leaves no observation, no connection and no counter it checks behind."""
    standing.service.reset()
    return standing


@pytest.fixture
def service() -> ContractService:
    return ContractService()


@pytest_asyncio.fixture(loop_scope="module")
async def server(transport: TransportInfo, service: ContractService) -> AsyncIterator[ServerTransport]:
    srv = await start(transport, service)
    yield srv
    await srv.aclose()


@pytest_asyncio.fixture(loop_scope="module")
async def client(transport: TransportInfo) -> AsyncIterator[ClientTransport]:
    cli = await transport.open_client(None, None, {})
    yield cli
    await cli.aclose()


async def ask(client: ClientTransport, server: ServerTransport, request: Request) -> Response:
    return await client.request(server.endpoint, request, timeout=ANSWER_S)


# =========================================================================== 1. request / response


async def test_server_reports_its_endpoint(transport: TransportInfo, pair: Pair) -> None:
    server = pair.server
    assert (server.endpoint.scheme, server.endpoint.host) == (transport.scheme, HOST)
    assert 0 < server.endpoint.port < 65536


#: Every method, with and without query, payload, formats and ETags.
REQUESTS = [
    Request(Method.GET, "/echo"),
    Request(Method.GET, "/echo", {"name": "Gucci_bag_14", "odd": "a;b=c|d%e?*$#", "empty": ""},
            accept=ContentFormat.CBOR, etags=(b"\xaa\xbb", b"12345678")),
    Request(Method.FETCH, "/echo", {"limit": "10"}, b"SELECT * WHERE { ?s ?p ?o }", ContentFormat.TEXT,
            ContentFormat.CBOR),
    Request(Method.POST, "/echo", {"a": "1", "b": "two"}, b"\x00\xffpayload", ContentFormat.CBOR, ContentFormat.JSON,
            etags=(b"\x09\x08",)),
    Request(Method.PUT, "/echo", payload=b"put"),
    Request(Method.DELETE, "/echo"),
    Request(Method.PATCH, "/echo", payload=b"patch", content_format=ContentFormat.CBOR),
    Request(Method.IPATCH, "/echo", payload=b"ipatch"),
]


async def test_a_request_arrives_whole_and_its_answer_too(pair: Pair) -> None:
    server, client, service = pair.server, pair.client, pair.service
    for request in REQUESTS:
        response = await ask(client, server, request)
        # method, path, query, payload, formats, ETags; no peer without security
        assert service.seen[-1] == request
        assert (response.status, response.content_format, response.max_age, response.etag) == (
            Status.CONTENT, ContentFormat.JSON, 42, b"\x01\x02\x03\x04"), request
        head, _, body = response.payload.partition(b"\n")
        assert json.loads(head)["method"] == str(request.method)
        assert body == request.payload
    assert distinct(service.seen) == REQUESTS


async def test_if_match_arrives(pair: Pair) -> None:
    """A conditional write (``coapkb update --if-match``, the KB's 4.12)
    depends on the service seeing If-Match."""
    request = Request(Method.IPATCH, "/echo", payload=b"patch", if_match=(b"\x01\x02\x03\x04\x05\x06\x07\x08",))
    await ask(pair.client, pair.server, request)
    assert distinct(pair.service.seen) == [request]


async def test_every_status_and_its_options_come_back(pair: Pair) -> None:
    for status in Status:
        response = await ask(pair.client, pair.server, Request(Method.GET, "/status", {"code": str(int(status))}))
        if status == Status.VALID:
            expected = Response(Status.VALID, b"", None, 3, b"\x05")
        else:
            expected = Response(status, f"status {status.dotted}".encode(), ContentFormat.TEXT, 3, b"\x05")
        assert response == expected


async def test_errors_unknown_paths_and_a_crashing_handler(pair: Pair) -> None:
    server, client = pair.server, pair.client
    error = await ask(client, server, Request(Method.GET, "/error"))
    assert (error.status, error.text(), error.content_format) == (Status.BAD_REQUEST, "bad query", ContentFormat.TEXT)
    missing = await ask(client, server, Request(Method.GET, "/nope"))
    assert missing.status is Status.NOT_FOUND
    crash = await ask(client, server, Request(Method.GET, "/crash"))
    assert crash.status is Status.INTERNAL_SERVER_ERROR
    again = await ask(client, server, Request(Method.GET, "/echo"))
    assert again.status is Status.CONTENT


async def test_concurrent_requests_get_their_own_answers(pair: Pair) -> None:
    server, client = pair.server, pair.client
    # Later requests finish first, so answers come back out of order.
    n = 40
    requests = [Request(Method.POST, "/slow", {"delay": f"{(n - i) * 0.002:.3f}"}, f"req-{i}".encode())
                for i in range(n)]
    responses = await asyncio.gather(*(ask(client, server, r) for r in requests))
    assert [r.payload for r in responses] == [r.payload for r in requests]


async def test_counters_agree_on_both_ends(server: ServerTransport, client: ClientTransport) -> None:
    request = Request(Method.POST, "/mirror", payload=b"x" * 300)
    response = await ask(client, server, request)
    c, s = client.counters, server.counters
    assert (c.messages_sent, c.messages_received, s.messages_received, s.messages_sent) == (1, 1, 1, 1)
    assert c.bytes_sent == s.bytes_received > len(request.payload)
    assert c.bytes_received == s.bytes_sent > len(response.payload)
    assert c.retransmissions == 0


async def test_port_in_use_is_a_transport_error(transport: TransportInfo, pair: Pair) -> None:
    server, client = pair.server, pair.client
    with pytest.raises(TransportError) as caught:
        await start(transport, ContractService(), server.endpoint.port)
    assert (await ask(client, server, Request(Method.GET, "/echo"))).status is Status.CONTENT  # unharmed
    message = str(caught.value)
    assert server.endpoint.hostport in message and "\n" not in message, message
    assert "in use" in message, message


# =========================================================================== 2. observe


async def test_observe_gives_the_first_value_then_each_change(
    server: ServerTransport, client: ClientTransport, service: ContractService
) -> None:
    values: list[bytes] = []
    async with contextlib.aclosing(observe(client, server.endpoint, Request(Method.GET, "/counter"))) as updates:
        async for response in updates:
            assert (response.status, response.content_format) == (Status.CONTENT, ContentFormat.TEXT)
            values.append(response.payload)
            if len(values) == 4:
                break
            assert observation_count(server) == 1
            service.bump()
    assert values == [b"0", b"1", b"2", b"3"]
    # The client still asks plain questions.
    assert (await ask(client, server, Request(Method.GET, "/counter"))).payload == b"3"


async def test_two_observers_see_the_same_changes(
    transport: TransportInfo, server: ServerTransport, client: ClientTransport, service: ContractService
) -> None:
    other = await transport.open_client(None, None, {})
    try:
        request = Request(Method.GET, "/counter")
        async with (
            contextlib.aclosing(observe(client, server.endpoint, request)) as a,
            contextlib.aclosing(observe(other, server.endpoint, request)) as b,
        ):
            assert [(await anext(a)).payload, (await anext(b)).payload] == [b"0", b"0"]
            assert observation_count(server) == 2
            for expected in (b"1", b"2"):
                service.bump()
                assert [(await anext(a)).payload, (await anext(b)).payload] == [expected, expected]
            await a.aclose()  # one goes; the other stays
            service.bump()
            assert (await anext(b)).payload == b"3"
    finally:
        await other.aclose()


async def test_a_burst_of_changes_reaches_a_slow_reader_as_increasing_states(
    server: ServerTransport, client: ClientTransport, service: ContractService
) -> None:
    async with contextlib.aclosing(observe(client, server.endpoint, Request(Method.GET, "/counter"))) as updates:
        assert (await anext(updates)).payload == b"0"
        for _ in range(20):
            service.bump()
        seen = [int((await anext(updates)).payload)]
        while seen[-1] != 20:
            seen.append(int((await asyncio.wait_for(anext(updates), ANSWER_S)).payload))
    assert seen == sorted(set(seen))


async def test_an_error_notification_ends_the_iteration_and_the_observation(
    server: ServerTransport, client: ClientTransport, service: ContractService
) -> None:
    updates = observe(client, server.endpoint, Request(Method.GET, "/counter"))
    assert (await anext(updates)).payload == b"0"
    service.broken = True
    service.bump()
    async with asyncio.timeout(ANSWER_S):
        rest = [r.status async for r in updates]
    assert rest == [Status.NOT_FOUND]
    await until(lambda: observation_count(server) == 0, "the observation ended by an error is dropped", FORGET_S)


async def test_closing_the_iterator_deregisters(
    server: ServerTransport, client: ClientTransport, service: ContractService
) -> None:
    """Both ways of closing (``break`` under ``aclosing``, ``aclose()``), one
    observation after the other: the server holds one, then none, and the
    service no subscription made for one."""
    subscriptions = len(service._subscribers)
    request = Request(Method.GET, "/counter")
    b = observe(client, server.endpoint, request)
    assert (await anext(b)).payload == b"0"
    async with contextlib.aclosing(observe(client, server.endpoint, request)) as a:
        async for _ in a:
            assert observation_count(server) == 2
            break
    await until(lambda: observation_count(server) == 1, "the first observation is deregistered", FORGET_S)
    await b.aclose()
    await until(lambda: observation_count(server) == 0, "the second observation is deregistered", FORGET_S)
    assert len(service._subscribers) == subscriptions


async def test_a_closed_observation_frees_its_slot(
    server: ServerTransport, client: ClientTransport, service: ContractService
) -> None:
    """More observations opened and closed one after the other than any
    transport keeps at once (for one client, one resource or the server):
    the last is still registered, and notified."""
    request = Request(Method.GET, "/counter")
    for _ in range(70):
        async with contextlib.aclosing(observe(client, server.endpoint, request)) as updates:
            assert (await anext(updates)).payload == b"0"
    async with contextlib.aclosing(observe(client, server.endpoint, request)) as updates:
        assert (await anext(updates)).payload == b"0"
        service.bump()
        change = await asyncio.wait_for(anext(updates, None), ANSWER_S)
        assert change is not None, "the iteration ended: the observation was not registered"
        assert change.payload == b"1"


async def test_observing_an_error_is_one_item(pair: Pair) -> None:
    items = [r async for r in observe(pair.client, pair.server.endpoint, Request(Method.GET, "/nope"))]
    assert [r.status for r in items] == [Status.NOT_FOUND]
    assert observation_count(pair.server) == 0


async def test_an_observer_whose_client_closes_is_forgotten(
    transport: TransportInfo, server: ServerTransport, service: ContractService
) -> None:
    """No deregistration can be sent: the server finds out (its connection
    closed, the subscriber went, or a notification could not be delivered)."""
    cli = await transport.open_client(None, None, {})
    updates = observe(cli, server.endpoint, Request(Method.GET, "/counter"))
    assert (await anext(updates)).payload == b"0"
    assert observation_count(server) == 1
    await cli.aclose()

    def forgotten() -> bool:
        service.bump()  # a change to notify: the way some servers find out
        return observation_count(server) == 0

    await until(forgotten, "the closed client's observation is forgotten")
    with contextlib.suppress(TransportError):
        await updates.aclose()


# =========================================================================== 3. garbage


_noise = random.Random(7252).randbytes  # the same garbage every run
#: What a stranger may send to a server's port: noise, and what other
#: protocols (CoAP, RTPS, QUIC, ZMTP, HTTP) look like, broken.
GARBAGE: list[bytes] = [
    b"",
    b"\x00" * 3,
    b"\xff",
    _noise(200),
    _noise(1200),
    bytes(1500),
    b"\xff" * 2000,
    b"\x40\x01\x00\x01",  # a CoAP GET header, no options
    b"\x44\x01\x00\x01\x01\x02\x03\x04\xf0",  # CoAP, reserved option delta
    b"RTPS",  # a truncated RTPS header
    b"RTPS\x02\x01\x01\x10" + _noise(12) + _noise(64),  # RTPS header, junk after it
    b"\xc0\x00\x00\x00\x01" + _noise(1195),  # a QUIC v1 long header ("Initial"), then noise
    b"\xc0\x0a\x0a\x0a\x0a\x08" + _noise(8) + b"\x08" + _noise(8) + bytes(1180),  # unknown QUIC version
    b"\x40" + _noise(40),  # a QUIC short header for a connection nobody has
    b"\xff" + bytes(8) + b"\x7f\x09" + _noise(54),  # a ZMTP greeting of an unknown version
    b"GET / HTTP/1.1\r\nHost: robot\r\n\r\n",
]


async def _spray(transport: TransportInfo, peer: Endpoint) -> None:
    """Every piece of :data:`GARBAGE` at ``peer``'s port, 5 times over: as
    datagrams, or on TCP connections (one per piece, and one with all of it)."""
    if transport.datagram:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for _ in range(5):
                for datagram in GARBAGE:
                    s.sendto(datagram, (peer.host, peer.port))
        return
    for pieces in [[piece] for piece in GARBAGE if piece] * 5 + [GARBAGE]:
        _, writer = await asyncio.open_connection(peer.host, peer.port)
        try:
            for piece in pieces:
                writer.write(piece)
            with contextlib.suppress(ConnectionError):
                await writer.drain()
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()


async def test_garbage_at_the_port_leaves_the_server_answering(
    transport: TransportInfo, server: ServerTransport, client: ClientTransport
) -> None:
    before = await ask(client, server, Request(Method.GET, "/echo"))
    assert before.status is Status.CONTENT
    # A connection that says nothing holds nothing up.
    silent = None
    if not transport.datagram:
        silent = await asyncio.open_connection(server.endpoint.host, server.endpoint.port)
    try:
        await _spray(transport, server.endpoint)
        # The client that asked before the garbage, and a new one, are both answered.
        again = await ask(client, server, Request(Method.GET, "/echo", payload=b"again"))
        fresh_client = await transport.open_client(None, None, {})
        try:
            fresh = await ask(fresh_client, server, Request(Method.GET, "/echo", payload=b"fresh"))
        finally:
            await fresh_client.aclose()
    finally:
        if silent is not None:
            silent[1].close()
            with contextlib.suppress(ConnectionError):
                await silent[1].wait_closed()
    assert (again.status, again.payload.endswith(b"again")) == (Status.CONTENT, True)
    assert (fresh.status, fresh.payload.endswith(b"fresh")) == (Status.CONTENT, True)
    if transport.datagram:
        # A datagram not of the protocol is dropped below coapkb's parser
        # (QUIC, RTPS), or answered by it (CoAP, which counts none).  Over
        # TCP some reaches it: ZeroMQ takes bytes without a greeting as
        # ZMTP 1.0 frames, then counts each as malformed.
        assert getattr(server, "malformed", 0) == 0


# =========================================================================== 4. dead and unreachable peers


@pytest_asyncio.fixture(loop_scope="module")
async def asker(transport: TransportInfo) -> AsyncIterator[ClientTransport]:
    """A client for asking dead peers (:func:`open_for_dead_peers`)."""
    cli = await open_for_dead_peers(transport)
    yield cli
    await cli.aclose()


async def test_a_port_nobody_listens_on_is_unreachable(transport: TransportInfo, asker: ClientTransport) -> None:
    peer = local(transport, unused_port(transport))
    await unreachable(asker, peer, Request(Method.GET, "/echo"))
    # and again on the same client: nothing of the first attempt hangs around
    await unreachable(asker, peer, Request(Method.GET, "/echo"))


async def test_a_server_that_closed_is_unreachable(
    transport: TransportInfo, asker: ClientTransport, service: ContractService
) -> None:
    srv = await start(transport, service)
    peer = srv.endpoint
    assert (await asker.request(peer, Request(Method.GET, "/echo"), timeout=ANSWER_S)).status is Status.CONTENT
    await srv.aclose()
    await unreachable(asker, peer, Request(Method.GET, "/echo"))  # a client that knew it
    fresh = await open_for_dead_peers(transport)
    try:
        await unreachable(fresh, peer, Request(Method.GET, "/echo"))  # and one that did not
    finally:
        await fresh.aclose()


async def test_observing_a_port_nobody_listens_on_is_unreachable(
    transport: TransportInfo, asker: ClientTransport
) -> None:
    peer = local(transport, unused_port(transport))
    async with asyncio.timeout(SHORT_S + LATE_S):
        with pytest.raises(PeerUnreachable):
            async for _ in observe(asker, peer, Request(Method.GET, "/counter"), timeout=SHORT_S):
                pass


async def test_a_client_closes_promptly_after_an_unreachable_peer(transport: TransportInfo) -> None:
    """The registry's own client: whatever it was still trying towards a
    peer that never answered, closing does not wait for it."""
    cli = await transport.open_client(None, None, {})
    closing: asyncio.Task[None] | None = None
    try:
        await unreachable(cli, local(transport, unused_port(transport)), Request(Method.GET, "/echo"))
    finally:
        closing = asyncio.ensure_future(cli.aclose())
        started = time.monotonic()
        done, _ = await asyncio.wait([closing], timeout=CLOSE_S)
        if not done:
            await closing  # it ends in the end: let it, before failing
    assert done, f"aclose took {time.monotonic() - started:.1f}s"


async def test_a_slow_answer_times_out_and_the_server_answers_again(pair: Pair) -> None:
    server, client, service = pair.server, pair.client, pair.service
    late = await unreachable(client, server.endpoint, Request(Method.GET, "/hold"), timeout=0.3)
    assert service.handling.is_set()  # it arrived: the budget ran out on the answer
    assert isinstance(late, PeerTimeout) and "within 0.3s" in str(late), repr(late)
    assert (await ask(client, server, Request(Method.GET, "/echo"))).status is Status.CONTENT


async def test_a_request_that_timed_out_is_not_delivered_later(
    transport: TransportInfo, asker: ClientTransport, service: ContractService
) -> None:
    """Once somebody listens there, only the new request arrives: the one
    that timed out was not kept in a queue for a later connection."""
    peer = local(transport, unused_port(transport))
    await unreachable(asker, peer, Request(Method.POST, "/mirror", payload=b"stale"))
    srv = await start(transport, service, peer.port)
    try:
        fresh = await asker.request(peer, Request(Method.POST, "/mirror", payload=b"fresh"), timeout=ANSWER_S)
        assert fresh.payload == b"fresh"
        assert distinct([r.payload for r in service.seen]) == [b"fresh"]
    finally:
        await srv.aclose()


async def test_a_closed_client_fails_its_pending_request_and_refuses_more(
    transport: TransportInfo, server: ServerTransport, service: ContractService
) -> None:
    cli = await transport.open_client(None, None, {})
    pending = asyncio.create_task(cli.request(server.endpoint, Request(Method.GET, "/hold"), timeout=ANSWER_S))
    await asyncio.wait_for(service.handling.wait(), ANSWER_S)  # the request reached the server
    await cli.aclose()
    with pytest.raises(TransportError):
        await asyncio.wait_for(pending, LATE_S)
    with pytest.raises(TransportError):
        await cli.request(server.endpoint, Request(Method.GET, "/echo"), timeout=SHORT_S)


async def test_a_closed_client_says_so(transport: TransportInfo, pair: Pair) -> None:
    cli = await transport.open_client(None, None, {})
    await cli.aclose()
    with pytest.raises(TransportError, match="closed"):
        await cli.request(pair.server.endpoint, Request(Method.GET, "/echo"), timeout=SHORT_S)


async def test_a_closed_clients_observation_ends(
    transport: TransportInfo, server: ServerTransport, service: ContractService
) -> None:
    """Whoever iterates over an observation of a client that closes gets a
    TransportError, not a wait for ever."""
    cli = await transport.open_client(None, None, {})
    updates = observe(cli, server.endpoint, Request(Method.GET, "/counter"))
    try:
        assert (await anext(updates)).payload == b"0"
        await cli.aclose()
        with pytest.raises(TransportError):
            await asyncio.wait_for(anext(updates), SHORT_S)
    finally:
        with contextlib.suppress(Exception):
            await updates.aclose()


# =========================================================================== 5. size


async def test_a_large_request_and_a_large_answer_arrive_intact(pair: Pair) -> None:
    server, client, service = pair.server, pair.client, pair.service
    # 512 kB each way is 500 block round trips over CoAP: the timeout bounds a hang, on a busy machine too.
    mirrored = await client.request(server.endpoint, Request(Method.POST, "/mirror", payload=LARGE,
                                                             content_format=ContentFormat.CBOR), timeout=60)
    assert (mirrored.status, mirrored.content_format, mirrored.payload == LARGE) == (
        Status.CHANGED, ContentFormat.CBOR, True)
    assert service.seen[-1].payload == LARGE
    large = await client.request(server.endpoint, Request(Method.GET, "/large"), timeout=60)
    assert (large.status, large.payload == LARGE) == (Status.CONTENT, True)


async def test_an_oversized_request_is_carried_or_refused(pair: Pair) -> None:
    """Over a server's limit a request is refused: an error answer, or no
    answer within its budget (ZeroMQ drops the connection); never a hang,
    never part of it handed to the service.  Without a limit it arrives
    intact.  Either way the server answers the next request."""
    server, client, service = pair.server, pair.client, pair.service
    try:
        answer = await client.request(server.endpoint, Request(Method.POST, "/mirror", payload=HUGE), timeout=1.5)
    except TransportError:
        pass
    else:
        assert answer.status == Status.CHANGED and answer.payload == HUGE or answer.status >= 400, answer.status
    assert all(r.payload == HUGE for r in service.seen), "the service got part of the request"
    assert (await ask(client, server, Request(Method.GET, "/echo"))).status is Status.CONTENT


# =========================================================================== 6. security


@pytest.fixture(scope="module")
def teams(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Two teams: ``coapkb keys``'s files for three robots, the feeder, central and operator each."""
    root = tmp_path_factory.mktemp("teams")
    for name in ("ours", "theirs"):
        generate_team(root / name, default_members(3))
    return root / "ours", root / "theirs"


async def test_only_the_team_gets_answers(
    transport: TransportInfo, service: ContractService, teams: tuple[Path, Path]
) -> None:
    """Without the team's credentials, or with another team's, a client gets
    no answer from the service (an error, or a 4.01); a member gets one, in
    its own name."""
    if transport.security is None:
        not_applicable(f"{transport.scheme} cannot be secured: {transport.unsecurable_because}")
    ours, theirs = teams
    robot1 = server_security(transport.scheme, load_identity(ours, "Robot1"))
    srv = await serve(service, local(transport), security=robot1)
    expected = {srv.endpoint.hostport: "Robot1"}
    try:
        strangers: dict[str, Any] = {
            "no credentials": None,
            "another team's": client_security(transport.scheme, load_identity(theirs, "feeder"), expected),
        }
        for who, security in strangers.items():
            cli = await open_client(transport.scheme, security=security)
            try:
                async with asyncio.timeout(STRANGER_S + LATE_S):
                    response = await cli.request(srv.endpoint, Request(Method.GET, "/echo"), timeout=STRANGER_S)
            except TransportError:
                pass  # no session, handshake refused, or no answer at all
            else:
                assert response.status == Status.UNAUTHORIZED, (who, response)
            finally:
                await cli.aclose()
        assert service.seen == [], "a stranger's request reached the service"
        member = await open_client(transport.scheme, security=client_security(
            transport.scheme, load_identity(ours, "feeder"), expected))
        try:
            answer = await member.request(srv.endpoint, Request(Method.GET, "/echo"), timeout=ANSWER_S)
        finally:
            await member.aclose()
        assert answer.status is Status.CONTENT
        assert distinct([r.peer for r in service.seen]) == ["feeder"]
    finally:
        await srv.aclose()


# =========================================================================== 7. admit


async def test_the_services_refusal_reaches_the_client_unchanged(pair: Pair) -> None:
    server, client, service = pair.server, pair.client, pair.service
    service.refused.add("/guarded")
    for method in (Method.GET, Method.POST):
        response = await ask(client, server, Request(method, "/guarded", payload=b"x" if method == Method.POST else b""))
        assert response == REFUSAL
    assert service.seen == []  # asked before anything else: the service never saw it
    assert distinct(service.asked) == [(None, "GET", "/guarded"), (None, "POST", "/guarded")]


async def test_a_refused_observation_is_one_item(pair: Pair) -> None:
    server, client, service = pair.server, pair.client, pair.service
    service.refused.add("/guarded")
    items = [r async for r in observe(client, server.endpoint, Request(Method.GET, "/guarded"))]
    assert items == [REFUSAL]
    assert service.seen == []
    assert observation_count(server) == 0


# =========================================================================== the list of known bugs


async def test_each_known_bug_names_a_case_and_a_transport() -> None:
    cases = {name for name in globals() if name.startswith("test_")}
    assert set(KNOWN_BUGS) <= cases and SLOW_TO_FAIL <= set(KNOWN_BUGS)
    assert {scheme for bugs in KNOWN_BUGS.values() for scheme in bugs} <= {t.scheme for t in REGISTERED}
