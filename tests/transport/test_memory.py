"""The in-memory transport keeps the interface's promises: timeouts, unreachable peers, Observe."""

from __future__ import annotations

import asyncio

import pytest

from coapkb.transport.base import Endpoint, PeerUnreachable, ResourceInfo
from coapkb.transport.memory import MemoryNetwork
from coapkb.transport.messages import Method, Request, Response, Status
from coapkb.transport.router import Router

HERE = Endpoint("coap", "robot-a", 1)


def _router(answers: list[bytes], stall: asyncio.Event | None = None) -> Router:
    router = Router()

    async def get(request: Request) -> Response:
        if stall is not None:
            await stall.wait()
        return Response(Status.CONTENT, answers[-1])

    router.add(ResourceInfo("/x", obs=True), get)
    return router


async def test_request_reaches_the_service_and_counts_payloads() -> None:
    net = MemoryNetwork()
    server = await net.serve(_router([b"hello"]), HERE)
    client = net.client()
    response = await client.request(HERE, Request(Method.GET, "/x", payload=b"ab"), timeout=1)
    assert (response.status, response.payload) == (Status.CONTENT, b"hello")
    assert (client.counters.bytes_sent, client.counters.bytes_received) == (2, 5)
    assert (server.counters.messages_received, server.counters.bytes_sent) == (1, 5)
    missing = await client.request(HERE, Request(Method.GET, "/nope"), timeout=1)
    assert missing.status == Status.NOT_FOUND


async def test_unknown_closed_and_silent_peers_are_unreachable() -> None:
    net = MemoryNetwork()
    client = net.client()
    with pytest.raises(PeerUnreachable, match="nobody listens"):
        await client.request(HERE, Request(Method.GET, "/x"), timeout=1)
    server = await net.serve(_router([b"v"], stall=asyncio.Event()), HERE)
    with pytest.raises(PeerUnreachable, match="within 0.05s"):
        await client.request(HERE, Request(Method.GET, "/x"), timeout=0.05)
    await server.aclose()
    with pytest.raises(PeerUnreachable):
        await client.request(HERE, Request(Method.GET, "/x"), timeout=1)
    await net.serve(Router(), HERE)
    with pytest.raises(OSError, match="in use"):
        await net.serve(Router(), HERE)


async def test_observe_yields_the_state_then_each_change_and_ends_when_the_server_closes() -> None:
    net = MemoryNetwork()
    answers = [b"1"]
    router = _router(answers)
    server = await net.serve(router, HERE)
    seen: list[bytes] = []
    got = asyncio.Condition()

    async def watch() -> None:
        async for response in net.client().observe(HERE, Request(Method.GET, "/x")):
            async with got:
                seen.append(response.payload)
                got.notify_all()

    watcher = asyncio.create_task(watch())
    async with got:
        await asyncio.wait_for(got.wait_for(lambda: seen == [b"1"]), 1)
    answers.append(b"2")
    router.notify("/x")
    async with got:
        await asyncio.wait_for(got.wait_for(lambda: seen == [b"1", b"2"]), 1)
    await server.aclose()
    with pytest.raises(PeerUnreachable, match="closed"):
        await asyncio.wait_for(watcher, 1)
