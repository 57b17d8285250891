"""Facts pushed by their holder (coapkb.agent.fact_push), over CoAP on
loopback with real sockets: a teammate that observes the holder takes the
answer it would have asked for, and asks nothing; one that gets no push in
time asks, and gets the same answer."""

from __future__ import annotations

import asyncio
import dataclasses
from collections.abc import AsyncIterator
from typing import Any

import pytest
import pytest_asyncio
from agent_helpers import HOLDERS, config
from support import free_udp_port

from coapkb.agent.fact_push import FactPusher, PushedFacts, facts_path
from coapkb.agent.query_handler import QueryHandler
from coapkb.config import Teammate
from coapkb.kb.client import KBClient
from coapkb.kb.resources import KBResources
from coapkb.kb.store import KnowledgeBase
from coapkb.transport import open_client, serve
from coapkb.transport.base import ClientTransport, Endpoint, ServerTransport
from coapkb.transport.messages import ContentFormat, Method, Request, Status
from coapkb.transport.router import Router
from coapkb.wire.codec import decode_cbor
from coapkb.wire.pushed import decode_pushed, request_key

#: Generous: a loaded machine.
PATIENCE_S = 10.0
OBJECT = {"name": "Gucci_bag_14"}
OTHER_OBJECT = {"name": "Lenovo_tv_125"}


class Holder:
    """Robot2, holding the Object KB, served over CoAP with its pusher."""

    def __init__(self, kb: KnowledgeBase, endpoint: Endpoint) -> None:
        self.router = Router()
        KBResources(kb).mount(self.router)
        self.pusher = FactPusher(self.router, ("Object",))
        self.endpoint = endpoint
        self.server: ServerTransport | None = None


@pytest_asyncio.fixture
async def holder(kbs: dict[str, KnowledgeBase]) -> AsyncIterator[Holder]:
    robot2 = Holder(kbs["Object"], Endpoint("coap", "127.0.0.1", free_udp_port()))
    robot2.server = await serve(robot2.router, robot2.endpoint)
    yield robot2
    await robot2.server.aclose()


@pytest_asyncio.fixture
async def client() -> AsyncIterator[ClientTransport]:
    transport = await open_client("coap")
    yield transport
    await transport.aclose()


@pytest_asyncio.fixture
async def robot1(client: ClientTransport, holder: Holder) -> AsyncIterator[QueryHandler]:
    """Robot1 (Location), reading the Object KB from ``holder`` and observing its pushes."""
    team: dict[str, Any] = {r: Teammate(r, holder.endpoint if r == "Robot2" else Endpoint("coap", "127.0.0.1", 9),
                                        (kb,)) for r, kb in HOLDERS.items()}
    cfg = dataclasses.replace(config("Robot1"), team=team, query_timeout_s=PATIENCE_S)
    queries = QueryHandler(cfg, None, KBClient(client, cache=True))
    queries.pushed = pushed = PushedFacts(client, {"Object": ("Robot2", holder.endpoint)})
    pushed.start()
    try:
        async with asyncio.timeout(PATIENCE_S):
            await pushed.observing(holder.endpoint)
        yield queries
    finally:
        await pushed.aclose()


async def test_a_pushed_answer_is_taken_and_nothing_is_asked(robot1: QueryHandler, holder: Holder) -> None:
    assert holder.server is not None
    received = holder.server.counters.messages_received
    holder.pusher.begin(1)
    await holder.pusher.offer("Object", "pick-facts", OBJECT)
    result = await robot1.run("pick-facts", OBJECT)
    assert result.as_dicts()[0]["grip"] is not None  # type: ignore[union-attr]
    assert (robot1.stats.pushed, robot1.stats.cached, robot1.stats.remote) == (1, 1, 0)
    # The notification's ACK at most (every 16th is confirmable); no request.
    assert holder.server.counters.messages_received - received <= 1


async def test_without_a_push_in_time_the_teammate_asks(robot1: QueryHandler, holder: Holder,
                                                         client: ClientTransport) -> None:
    assert robot1.pushed is not None
    asked = await robot1.run("pick-facts", OBJECT)  # the holder never offers it
    assert (robot1.stats.pushed, robot1.stats.remote, robot1.pushed.missed) == (0, 1, 1)
    holder.pusher.begin(1)
    await holder.pusher.offer("Object", "pick-facts", OBJECT)
    response = await client.request(holder.endpoint, Request(Method.GET, facts_path("Object"),
                                                             accept=ContentFormat.CBOR), timeout=PATIENCE_S)
    assert response.status == Status.CONTENT
    (pushed,) = decode_pushed(response.payload)
    assert decode_cbor(pushed.result) == asked  # the same answer either way


async def test_an_answer_the_teammates_still_hold_is_not_pushed_again(holder: Holder) -> None:
    notified: asyncio.Queue[None] = asyncio.Queue()
    holder.router.subscribe(facts_path("Object"), lambda: notified.put_nowait(None))
    holder.pusher.begin(1)
    await holder.pusher.offer("Object", "pick-facts", OBJECT)
    async with asyncio.timeout(PATIENCE_S):
        await notified.get()
    holder.pusher.begin(2)
    await holder.pusher.offer("Object", "pick-facts", OBJECT)  # the same object again, within its Max-Age
    await holder.pusher.offer("Object", "pick-facts", OTHER_OBJECT)
    async with asyncio.timeout(PATIENCE_S):
        await notified.get()
    # Task 2's notification carries the other object's answer alone.
    response = await holder.router.handle(Request(Method.GET, facts_path("Object"), accept=ContentFormat.CBOR))
    assert [a.key for a in decode_pushed(response.payload)] == [request_key("pick-facts", OTHER_OBJECT)]
    assert notified.empty()


async def test_a_closing_holder_sends_no_notification_still_due(holder: Holder) -> None:
    notified: list[None] = []
    holder.router.subscribe(facts_path("Object"), lambda: notified.append(None))
    holder.pusher.begin(1)
    await holder.pusher.offer("Object", "pick-facts", OBJECT)
    holder.pusher.close()
    # Callbacks run in the order they were scheduled: once this one has
    # run, so has the turn the notification was due in.
    turn_over = asyncio.get_running_loop().create_future()
    asyncio.get_running_loop().call_soon(turn_over.set_result, None)
    await turn_over
    assert notified == []


async def test_a_holder_catching_up_answers_a_registration_once_caught_up() -> None:
    """The pushed answers are a read of the module: a restarted holder
    answers them, as its queries, only once it has caught up."""
    waiting, caught_up = asyncio.Event(), asyncio.Event()

    async def catching_up() -> None:
        waiting.set()
        await caught_up.wait()

    router = Router()
    FactPusher(router, ("Object",), catching_up)
    asking = asyncio.ensure_future(router.handle(Request(Method.GET, facts_path("Object"))))
    async with asyncio.timeout(PATIENCE_S):
        await waiting.wait()  # the answer waits on the catch-up
    assert not asking.done()
    caught_up.set()
    async with asyncio.timeout(PATIENCE_S):
        response = await asking
    assert response.status == Status.CONTENT and not decode_pushed(response.payload)


@pytest.mark.parametrize("module", ["Location", "Capability"])
async def test_a_module_the_holder_lacks_has_no_resource(holder: Holder, client: ClientTransport,
                                                         module: str) -> None:
    response = await client.request(holder.endpoint, Request(Method.GET, facts_path(module)), timeout=PATIENCE_S)
    assert response.status == Status.NOT_FOUND


async def test_the_wait_learns_how_late_pushes_come(robot1: QueryHandler, holder: Holder) -> None:
    pushed = robot1.pushed
    assert pushed is not None and pushed.expected_within("pick-facts") is None  # nothing awaited yet
    for task, name in enumerate(("Gucci_bag_14", "Canon_tv_538", "Barilla_pasta_1", "Muji_lamp_793"), 1):
        async def offer_late(task: int = task, name: str = name) -> None:
            await asyncio.sleep(0.05)  # the holder's own task comes 50 ms after this robot's
            holder.pusher.begin(task)
            await holder.pusher.offer("Object", "pick-facts", {"name": name})

        late = asyncio.create_task(offer_late())
        assert await pushed.wait(holder.endpoint, "pick-facts", {"name": name}, PATIENCE_S) is not None
        await late
    usual = pushed.expected_within("pick-facts")
    assert usual is not None and 1.5 * 0.05 <= usual < PATIENCE_S


async def test_a_holder_gone_after_it_was_observed_counts_as_a_failure(kbs: dict[str, KnowledgeBase],
                                                                        client: ClientTransport) -> None:
    """Nobody listening where a holder was observed is a failure for the
    failure detector, like a failed query (simulator seed 1567 of the
    rejoin profile: a holder that died between two tasks was otherwise
    found down only by a wait for its plan, after another teammate died);
    nobody listening where none was ever observed is a teammate not up yet."""
    gone: list[str] = []
    robot2_gone = asyncio.Event()

    async def on_gone(robot_id: str, exc: Exception) -> None:
        gone.append(robot_id)
        if robot_id == "Robot2":
            robot2_gone.set()

    holder = Holder(kbs["Object"], Endpoint("coap", "127.0.0.1", free_udp_port()))
    server = await serve(holder.router, holder.endpoint)
    never_up = Endpoint("coap", "127.0.0.1", free_udp_port())
    pushed = PushedFacts(client, {"Object": ("Robot2", holder.endpoint), "Location": ("Robot3", never_up)},
                         on_gone=on_gone)
    pushed.start()
    try:
        async with asyncio.timeout(PATIENCE_S):
            await pushed.observing(holder.endpoint)
            assert gone == []
            await server.aclose()
            pushed._start_watch("Object")  # registered again (after missed pushes): nobody there now
            await robot2_gone.wait()
        assert "Robot3" not in gone
    finally:
        await pushed.aclose()
