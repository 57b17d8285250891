"""Observations that notice when their server lost them.

A server sends an unchanged answer again before its Max-Age runs out, so an
observer's copy stays fresh and its silence means something
(:func:`coapkb.transport.observation.refresh_after`); an observer that hears
nothing for Max-Age and a margin registers again, and keeps trying while the
server is gone (:func:`coapkb.transport.observation.observe_fresh`).  Here
in-process servers on real sockets are closed and started again on the same
port; tests/kb/test_observe_restart.py kills a ``coapkb serve`` process.

Every wait is on the thing itself (an answer, a notice), bounded; none is a sleep.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable

import pytest
from support import free_tcp_port, free_udp_port

from coapkb import clock
from coapkb.transport import open_client, serve
from coapkb.transport.base import ClientTransport, Endpoint, PeerGone, ResourceInfo, ServerTransport, Service
from coapkb.transport.memory import MemoryNetwork
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status
from coapkb.transport.observation import (
    FRESHNESS_MARGIN_S,
    REREGISTER_TIMEOUT_S,
    Notice,
    observe_fresh,
    refresh_after,
)

VALUE = Request(Method.GET, "/value")
#: The Max-Age of the answers, seconds.
MAX_AGE = 1
#: Room for a busy machine's late event loop: the figures themselves
#: (within Max-Age and a second) are measured and reported, not tested.
LOAD_SLACK_S = 2.0
#: Bound of a wait that must end (an answer on loopback, a loaded machine).
WAIT_S = 10.0


class ValueService(Service):
    """``/value``: a text value with Max-Age :data:`MAX_AGE`, observable and
    quiet (observers hear of an answer that changed); ``unavailable`` answers 5.03."""

    def __init__(self, value: str = "0") -> None:
        self.value = value
        self.unavailable = 0
        self._subscribers: list[Callable[[], None]] = []

    def resources(self) -> list[ResourceInfo]:
        return [ResourceInfo("/value", obs=True, quiet=True)]

    async def handle(self, request: Request) -> Response:
        if request.path != "/value":
            return Response.error(Status.NOT_FOUND, "no such resource")
        if self.unavailable:
            self.unavailable -= 1
            return Response.error(Status.SERVICE_UNAVAILABLE, "starting", max_age=1)
        return Response(Status.CONTENT, self.value.encode(), ContentFormat.TEXT, max_age=MAX_AGE)

    def subscribe(self, path: str, on_change: Callable[[], None]) -> Callable[[], None]:
        self._subscribers.append(on_change)
        return lambda: self._subscribers.remove(on_change)

    def set(self, value: str) -> None:
        self.value = value
        for notify in list(self._subscribers):
            notify()


class Watch:
    """An :func:`observe_fresh` read by a task: its answers and its notices, in order."""

    def __init__(self, client: ClientTransport, peer: Endpoint, request: Request = VALUE) -> None:
        self.events: asyncio.Queue[tuple[str, str, float]] = asyncio.Queue()
        self._task = asyncio.ensure_future(self._read(client, peer, request))

    def _notice(self, notice: Notice) -> None:
        self.events.put_nowait((notice.kind, str(notice), clock.monotonic()))

    async def _read(self, client: ClientTransport, peer: Endpoint, request: Request) -> None:
        async with contextlib.aclosing(observe_fresh(client, peer, request, on_notice=self._notice)) as answers:
            async for response in answers:
                self.events.put_nowait(("answer", response.text(), clock.monotonic()))

    async def next(self, timeout: float = WAIT_S) -> tuple[str, str, float]:
        return await asyncio.wait_for(self.events.get(), timeout)

    async def until(self, kind: str, text: str | None = None, timeout: float = WAIT_S) -> tuple[list[str], float]:
        """Events up to the first of ``kind`` (with ``text``), and when that one came."""
        seen: list[str] = []
        async with asyncio.timeout(timeout):
            while True:
                got, line, at = await self.events.get()
                seen.append(f"{got}: {line}")
                if got == kind and (text is None or line == text):
                    return seen, at

    async def aclose(self) -> None:
        self._task.cancel()
        await asyncio.gather(self._task, return_exceptions=True)


SCHEMES = {"coap": free_udp_port, "zmq": free_tcp_port}
#: How long a client may take to be connected again once the server is
#: back: ZeroMQ reconnects at most every 2 s (``reconnect_ivl_max_ms``).
RECONNECT_S = {"coap": 0.0, "zmq": 2.0}


@pytest.fixture(params=sorted(SCHEMES))
async def endpoint(request: pytest.FixtureRequest) -> Endpoint:
    return Endpoint(request.param, "127.0.0.1", SCHEMES[request.param]())


@pytest.fixture
async def client(endpoint: Endpoint) -> AsyncIterator[ClientTransport]:
    transport = await open_client(endpoint.scheme)
    yield transport
    await transport.aclose()


async def test_an_unchanged_answer_is_sent_again_before_its_max_age_runs_out(
    endpoint: Endpoint, client: ClientTransport
) -> None:
    server = await serve(ValueService(), endpoint)
    try:
        async with contextlib.aclosing(client.observe(endpoint, VALUE)) as answers:  # type: ignore[type-var]
            first = await asyncio.wait_for(anext(answers), WAIT_S)
            got_first = clock.monotonic()
            again = await asyncio.wait_for(anext(answers), WAIT_S)
            waited = clock.monotonic() - got_first
            again_2 = await asyncio.wait_for(anext(answers), WAIT_S)
    finally:
        await server.aclose()
    assert first.payload == again.payload == again_2.payload == b"0"
    after = refresh_after(MAX_AGE)
    assert after is not None and after < MAX_AGE
    # Before the observer's copy goes stale, and not long before.
    assert after - 0.2 < waited < MAX_AGE + FRESHNESS_MARGIN_S + LOAD_SLACK_S, waited


async def _restart(endpoint: Endpoint, server: ServerTransport, service: Service) -> ServerTransport:
    await server.aclose()
    return await serve(service, endpoint)


async def test_an_observation_registers_again_with_a_restarted_server(
    endpoint: Endpoint, client: ClientTransport
) -> None:
    """Restarted before the observer noticed: no notification within Max-Age
    and a margin, so it registers again, and gets the restarted server's state."""
    server = await serve(ValueService("0"), endpoint)
    watch = Watch(client, endpoint)
    try:
        assert (await watch.next())[:2] == ("answer", "0")
        server = await _restart(endpoint, server, ValueService("1"))
        serving = clock.monotonic()
        seen, at = await watch.until("answer", "1")
        assert seen == [f"re-registered: re-registered: no notification within Max-Age {MAX_AGE} s", "answer: 1"]
        assert at - serving < MAX_AGE + 1.0 + LOAD_SLACK_S, at - serving
    finally:
        await watch.aclose()
        await server.aclose()


async def test_an_observation_keeps_trying_while_its_server_is_gone(
    endpoint: Endpoint, client: ClientTransport
) -> None:
    """Down long enough to be noticed: one line for the loss, retries, and
    one for the server answering again; a change made on the restarted
    server comes within Max-Age and a second of it serving."""
    server = await serve(ValueService("0"), endpoint)
    watch = Watch(client, endpoint)
    try:
        assert (await watch.next())[:2] == ("answer", "0")
        await server.aclose()
        # Silence, then a re-registration that fails (ZeroMQ does not tell
        # a refused connection: its registration times out).
        seen, _ = await watch.until("lost", timeout=MAX_AGE + FRESHNESS_MARGIN_S + REREGISTER_TIMEOUT_S + WAIT_S)
        assert len(seen) == 1 and seen[0].startswith(f"lost: lost {endpoint}: ") and seen[0].endswith("; retrying")
        service = ValueService("0")
        server = await serve(service, endpoint)
        serving = clock.monotonic()
        service.set("1")  # before or after the observer is back: it sees it either way
        seen, at = await watch.until("answer", "1")
        assert seen[0].startswith(f"re-registered: re-registered: {endpoint} answers again, after "), seen
        assert at - serving < MAX_AGE + 1.0 + RECONNECT_S[endpoint.scheme] + LOAD_SLACK_S, at - serving
        service.set("2")  # and the observation goes on
        assert (await watch.until("answer", "2"))[0] == ["answer: 2"]
    finally:
        await watch.aclose()
        await server.aclose()


async def test_an_unchanged_answer_is_not_news() -> None:
    """A server that does not refresh (the in-memory one): the observer
    registers again after each Max-Age and a margin, and yields nothing
    while the answer stays the same."""
    net = MemoryNetwork()
    here = Endpoint("coap", "memory", 1)
    service = ValueService("0")
    server = await net.serve(service, here)
    watch = Watch(net.client(), here)
    try:
        assert (await watch.next())[:2] == ("answer", "0")
        for _ in range(2):
            kind, line, _ = await watch.next(timeout=MAX_AGE + FRESHNESS_MARGIN_S + WAIT_S)
            assert (kind, line) == ("re-registered", f"re-registered: no notification within Max-Age {MAX_AGE} s")
        service.set("1")
        assert (await watch.until("answer"))[0] == ["answer: 1"]
    finally:
        await watch.aclose()
        await server.aclose()


async def test_a_server_not_ready_yet_is_asked_again() -> None:
    """A restarted server answering 5.03 (not ready) is the server still
    missing, not the end of the observation."""
    net = MemoryNetwork()
    here = Endpoint("coap", "memory", 1)
    server = await net.serve(ValueService("0"), here)
    watch = Watch(net.client(), here)
    try:
        assert (await watch.next())[:2] == ("answer", "0")
        await server.aclose()
        service = ValueService("1")
        service.unavailable = 1
        server = await net.serve(service, here)
        seen, _ = await watch.until("answer")
        assert [line.split(":", 1)[0] for line in seen] == ["lost", "re-registered", "answer"], seen
        assert seen[-1] == "answer: 1"
    finally:
        await watch.aclose()
        await server.aclose()


async def test_the_first_registration_fails_as_before() -> None:
    """Nobody there at the start: the caller's error, not a retry."""
    net = MemoryNetwork()
    with pytest.raises(PeerGone):
        async for _ in observe_fresh(net.client(), Endpoint("coap", "memory", 1), VALUE):
            pass


async def test_an_error_answer_ends_the_observation() -> None:
    net = MemoryNetwork()
    here = Endpoint("coap", "memory", 1)
    server = await net.serve(ValueService("0"), here)
    try:
        answers = [r.status async for r in observe_fresh(net.client(), here, Request(Method.GET, "/nothing"))]
    finally:
        await server.aclose()
    assert len(answers) == 1 and not answers[0].is_success
