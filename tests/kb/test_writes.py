"""Writes on real sockets: PATCH/iPATCH ``/kb`` and what each mistake is
answered, observed queries, and replication between holders over every
transport that runs here."""

from __future__ import annotations

import asyncio
import random
from collections.abc import AsyncIterator
from dataclasses import dataclass

import pytest
from rdflib import Literal, URIRef
from support import ONTOLOGIES, free_tcp_port, free_udp_port

from coapkb.kb.client import KBClient, QueryFailed, WriteShort, decode
from coapkb.kb.limits import QueryLimits
from coapkb.kb.live import LiveKB, wall_ms
from coapkb.kb.replication import Holder, ReplicationSettings, Replicator
from coapkb.kb.resources import KBResources
from coapkb.kb.results import expect_select
from coapkb.kb.store import KnowledgeBase
from coapkb.kb.update import encode_patch
from coapkb.kb.write_concern import Ack
from coapkb.transport import open_client, serve
from coapkb.transport.base import Endpoint, ServerTransport
from coapkb.transport.messages import ContentFormat, Method, Request, Status
from coapkb.transport.observation import refresh_after
from coapkb.transport.router import Router

LOC = "http://www.tcs.org/2018/Location#"
PREFIX = f"PREFIX loc: <{LOC}>\n"
MOVE_ROBOT1 = PREFIX + (
    "DELETE { loc:Robot1 loc:Robot_aisle_no ?a } INSERT { loc:Robot1 loc:Robot_aisle_no %d } "
    "WHERE { loc:Robot1 loc:Robot_aisle_no ?a }"
)
AISLE_OF_ROBOT1 = PREFIX + "SELECT ?a WHERE { loc:Robot1 loc:Robot_aisle_no ?a }"


@dataclass
class Holding:
    live: LiveKB
    server: ServerTransport
    replicator: Replicator | None

    @property
    def endpoint(self) -> Endpoint:
        return self.server.endpoint


def _location(writer: str) -> LiveKB:
    return LiveKB(KnowledgeBase.load([ONTOLOGIES / "Location.owl"]), writer, wall_ms=wall_ms)


async def _hold(scheme: str, writer: str, port: int, holders: list[Holder], client=None,
                limits: QueryLimits | None = None) -> Holding:
    live = _location(writer)
    router = Router()
    replicator = None
    if client is not None:
        replicator = Replicator(live, client, holders, settings=ReplicationSettings(sync_every_s=0.3,
                                                                                     request_timeout_s=3,
                                                                                     ack_timeout_s=3),
                                rng=random.Random(1))
    KBResources(live, limits, replicator=replicator).mount(router)
    server = await serve(router, Endpoint(scheme, "127.0.0.1", port))
    return Holding(live, server, replicator)


@pytest.fixture
async def robot() -> AsyncIterator[Holding]:
    holding = await _hold("coap", "R.1", 0, [], limits=QueryLimits(max_update_bytes=2000))
    yield holding
    await holding.server.aclose()


async def _patch(peer: Endpoint, payload: bytes, *, method: Method = Method.PATCH, content_format: int = 0,
                 if_match: tuple[bytes, ...] = ()):
    client = await open_client("coap")
    try:
        return await client.request(peer, Request(method, "/kb", payload=payload, content_format=content_format,
                                                  if_match=if_match), timeout=10)
    finally:
        await client.aclose()


async def test_a_write_is_answered_2_04_with_the_new_version(robot: Holding) -> None:
    before = robot.live.etag
    response = await _patch(robot.endpoint, (MOVE_ROBOT1 % 4).encode())
    assert response.status == Status.CHANGED, response.text()
    assert response.etag == robot.live.etag != before
    assert response.text() == "removed 1, added 1; ack all (1 of 1 holder, in memory)"  # nobody else holds it
    [[aisle]] = robot.live.query(AISLE_OF_ROBOT1).rows  # type: ignore[union-attr]
    assert aisle == Literal(4)


@pytest.mark.parametrize(
    ("payload", "method", "content_format", "status", "says"),
    [
        (b"INSERT DATA { <http://a> <http://b> }", Method.PATCH, 0, Status.BAD_REQUEST, "line 1, column"),
        (b"LOAD <http://example.org/kb.ttl>", Method.PATCH, 0, Status.UNPROCESSABLE_ENTITY, "LOAD"),
        (PREFIX.encode() + b"INSERT DATA { loc:a loc:b _:c }", Method.PATCH, 0, Status.UNPROCESSABLE_ENTITY,
         "blank nodes"),
        (b"PREFIX obj: <http://www.tcs.org/2018/Object#> INSERT DATA { obj:a obj:b 1 }", Method.PATCH, 0,
         Status.UNPROCESSABLE_ENTITY, "does not hold the Object module"),
        ((MOVE_ROBOT1 % 2).encode(), Method.IPATCH, 0, Status.BAD_REQUEST, "not idempotent"),
        (b"x" * 2001, Method.PATCH, 0, Status.REQUEST_ENTITY_TOO_LARGE, "at most 2000"),
        (b"\xff\xfe", Method.PATCH, 0, Status.BAD_REQUEST, "not UTF-8"),
        (b"\xa1", Method.PATCH, 60, Status.BAD_REQUEST, "malformed patch"),
        (b"{}", Method.PATCH, 50, Status.UNSUPPORTED_CONTENT_FORMAT, "content-format 0"),
        (b"  ", Method.PATCH, 0, Status.BAD_REQUEST, "empty update"),
    ],
)
async def test_a_bad_write_gets_a_clear_answer_and_changes_nothing(
    robot: Holding, payload: bytes, method: Method, content_format: int, status: Status, says: str
) -> None:
    before = robot.live.etag
    response = await _patch(robot.endpoint, payload, method=method, content_format=content_format)
    assert response.status == status, response.text()
    assert says in response.text()
    assert robot.live.etag == before and not robot.live.changed


async def test_if_match_makes_a_write_conditional(robot: Holding) -> None:
    version = robot.live.etag
    assert (await _patch(robot.endpoint, (MOVE_ROBOT1 % 3).encode(), if_match=(version,))).status == Status.CHANGED
    stale = await _patch(robot.endpoint, (MOVE_ROBOT1 % 5).encode(), if_match=(version,))
    assert stale.status == Status.PRECONDITION_FAILED and version.hex() in stale.text()
    [[aisle]] = robot.live.query(AISLE_OF_ROBOT1).rows  # type: ignore[union-attr]
    assert aisle == Literal(3)


async def test_a_compact_patch_and_ipatch(robot: Holding) -> None:
    triple = (URIRef(LOC + "Shelf9"), URIRef(LOC + "note"), Literal("checked"))
    patch = encode_patch([], [triple])
    for _ in range(2):  # idempotent: applying it twice leaves one triple
        response = await _patch(robot.endpoint, patch, method=Method.IPATCH, content_format=ContentFormat.CBOR)
        assert response.status == Status.CHANGED, response.text()
    rows = robot.live.query(PREFIX + "SELECT ?n WHERE { loc:Shelf9 loc:note ?n }").rows  # type: ignore[union-attr]
    assert rows == ((Literal("checked"),),)


async def test_a_read_only_kb_refuses_writes() -> None:
    router = Router()
    KBResources(KnowledgeBase.load([ONTOLOGIES / "Location.owl"])).mount(router)
    server = await serve(router, Endpoint("coap", "127.0.0.1", 0))
    try:
        response = await _patch(server.endpoint, (MOVE_ROBOT1 % 4).encode())
        # Not the router's bare "PATCH not allowed": why, and how to make it writable.
        assert response.status == Status.METHOD_NOT_ALLOWED
        assert "read-only" in response.text() and "kb_writable" in response.text() and "--writable" in response.text()
    finally:
        await server.aclose()


async def test_an_observed_query_is_notified_when_its_answer_changes_only(robot: Holding) -> None:
    client = await open_client("coap")
    request = Request(Method.FETCH, "/kb/sparql", payload=AISLE_OF_ROBOT1.encode(), content_format=0)
    answers: asyncio.Queue = asyncio.Queue()
    loop = asyncio.get_running_loop()

    async def watch() -> None:
        async for response in client.observe(robot.endpoint, request):
            await answers.put((loop.time(), response.max_age, decode(response).rows))  # type: ignore[union-attr]

    watcher = asyncio.ensure_future(watch())
    try:
        last, max_age, rows = await asyncio.wait_for(answers.get(), 10)
        assert rows == ((Literal(9),),)
        refresh_s = refresh_after(max_age)
        robot.live.update(PREFIX + "INSERT DATA { loc:Shelf1 loc:note 'unrelated' }")
        # A round trip to the same server: a notification of the write would be out before its answer.
        await client.request(robot.endpoint, Request(Method.GET, "/.well-known/core"), timeout=10)
        robot.live.update(MOVE_ROBOT1 % 7)
        # The next notification is the move's: the unrelated write, made
        # first, sent none (it would have come first, with the old answer).
        # On a busy machine the steps can outlast the answer's freshness:
        # the server then sends it again, unchanged, a refresh apart.
        while True:
            at, _, rows = await asyncio.wait_for(answers.get(), 10)
            if rows != ((Literal(9),),) or refresh_s is None or at - last < 0.8 * refresh_s:
                break
            last = at
        assert rows == ((Literal(7),),)
        assert answers.empty()
    finally:
        watcher.cancel()
        await asyncio.gather(watcher, return_exceptions=True)
        await client.aclose()


# ------------------------------------------------------------------ replication


@pytest.mark.parametrize("scheme", ["coap", "zmq"])
async def test_three_holders_converge_over_the_transport(scheme: str) -> None:
    """Writes at every holder, one holder down for a while: every holder
    ends with the same version and answers, caught up by anti-entropy."""
    free = free_udp_port if scheme == "coap" else free_tcp_port
    ports = {name: free() for name in ("A", "B", "C")}
    endpoints = {name: Endpoint(scheme, "127.0.0.1", port) for name, port in ports.items()}
    client = await open_client(scheme)
    holdings: dict[str, Holding] = {}
    try:
        for name in ("A", "B"):
            holders = [Holder(n, endpoints[n], ("Location",)) for n in endpoints if n != name]
            holdings[name] = await _hold(scheme, f"{name}.1", ports[name], holders, client)
        kb = KBClient(client, timeout=10)
        # C is down: the write still lives on two robots (B acknowledged it).
        await kb.update(endpoints["A"], MOVE_ROBOT1 % 2)
        await kb.update(endpoints["B"], PREFIX + "INSERT DATA { loc:Mark1 loc:note 'b' }")
        holders = [Holder(n, endpoints[n], ("Location",)) for n in endpoints if n != "C"]
        holdings["C"] = await _hold(scheme, "C.1", ports["C"], holders, client)
        for holding in holdings.values():
            assert holding.replicator is not None
            holding.replicator.start()

        async def converged() -> None:
            while len({h.live.etag for h in holdings.values()}) > 1:
                await asyncio.sleep(0.1)

        await asyncio.wait_for(converged(), 20)  # C caught up with what it missed
        # A remove removes what the remover has seen: C has seen Mark1 now.
        await kb.update(endpoints["C"], PREFIX + "DELETE DATA { loc:Mark1 loc:note 'b' }")
        await asyncio.wait_for(converged(), 20)
        for holding in holdings.values():
            assert holding.live.query(AISLE_OF_ROBOT1).rows == ((Literal(2),),)  # type: ignore[union-attr]
            assert not holding.live.query(PREFIX + "ASK { loc:Mark1 ?p ?o }").value  # type: ignore[union-attr]
        replicas = [h.live.replicas["Location"] for h in holdings.values()]
        assert all(r.equal_to(replicas[0]) for r in replicas)
    finally:
        for holding in holdings.values():
            if holding.replicator is not None:
                await holding.replicator.aclose()
            await holding.server.aclose()
        await client.aclose()


async def test_a_write_tried_again_at_the_next_holder_is_made_once() -> None:
    """A writer whose first holder made a write but answered too late sends
    it, under the same id, to the next holder: the first holder's push
    carried the id, so the next answers it as a repeat and makes nothing."""
    client = await open_client("coap")
    ports = {name: free_udp_port() for name in ("A", "B")}
    endpoints = {name: Endpoint("coap", "127.0.0.1", port) for name, port in ports.items()}
    holdings: dict[str, Holding] = {}
    try:
        for name in ports:
            holders = [Holder(n, endpoints[n], ("Location",)) for n in endpoints if n != name]
            holdings[name] = await _hold("coap", f"{name}.1", ports[name], holders, client)
        kb = KBClient(client, timeout=10)
        wid = kb.new_write_id()
        first = await kb.write(endpoints["A"], MOVE_ROBOT1 % 2, write_id=wid)
        assert first.reached == Ack.ALL, first.text  # B confirmed it, and has its id
        version = holdings["B"].live.etag
        again = await kb.write(endpoints["B"], MOVE_ROBOT1 % 2, write_id=wid)
        assert again.text == "removed 1, added 1; ack 2 (made by A, which passed it on here)"
        assert again.version == version == holdings["B"].live.etag
        assert [h.live.replicas["Location"].context.vv for h in holdings.values()] == [{"A.1": 1}] * 2  # made once
        with pytest.raises(QueryFailed, match="4.22.*already used for another update"):
            await kb.write(endpoints["B"], MOVE_ROBOT1 % 3, write_id=wid)
        with pytest.raises(WriteShort, match="ack 2 .*asked all.*A made it and passed it on here"):
            await kb.write(endpoints["B"], MOVE_ROBOT1 % 2, write_id=wid, ack=Ack.ALL)
    finally:
        for holding in holdings.values():
            await holding.server.aclose()
        await client.aclose()


async def test_a_write_no_other_holder_confirms_is_said_so() -> None:
    client = await open_client("coap")
    nobody = Holder("B", Endpoint("coap", "127.0.0.1", free_udp_port()), ("Location",))
    holding = await _hold("coap", "A.1", 0, [nobody], client)
    try:
        with pytest.raises(WriteShort, match="5.04.*ack local .*, asked 2: written here.*; B (unreachable|did not answer)") as short:
            await KBClient(client, timeout=10).update(holding.endpoint, MOVE_ROBOT1 % 2)
        assert holding.live.changed  # written here all the same; it spreads when B answers
        assert short.value.version == holding.live.etag
    finally:
        await holding.server.aclose()
        await client.aclose()


async def test_a_garbage_sync_message_is_refused_and_changes_nothing(robot: Holding) -> None:
    client = await open_client("coap")
    router_has_sync = Request(Method.POST, "/kb/sync", payload=b"\x83\x00\x00", content_format=60)
    try:
        holding = await _hold("coap", "A.1", 0, [], client)
        response = await client.request(holding.endpoint, router_has_sync, timeout=10)
        assert response.status == Status.BAD_REQUEST and "malformed sync message" in response.text()
        assert not holding.live.changed
        await holding.server.aclose()
    finally:
        await client.aclose()


def test_inserting_a_triple_that_is_there_keeps_the_version() -> None:
    """A retried iPATCH adds nothing: no delta, the same ETag, so a later
    If-Match that names it still holds."""
    live = _location("Robot1.1")
    text = "PREFIX loc: <http://www.tcs.org/2018/Location#> INSERT DATA { loc:Pallet_9 loc:holds loc:Box_1 }"
    first = live.update(text)
    again = live.update(text)
    assert first.added == 1 and again.added == 0 and not again.deltas and again.version == first.version


def test_a_property_the_ontology_declares_functional_keeps_one_value() -> None:
    """``owl:FunctionalProperty`` in a module's files makes a property
    single-valued: the newest write's value shows, alone."""
    import pyoxigraph as ox

    kb = KnowledgeBase.load([ONTOLOGIES / "Location.owl"])
    colour = "http://www.tcs.org/2018/Location#Pallet_colour"
    kb.engine.store.add(ox.Quad(ox.NamedNode(colour), ox.NamedNode("http://www.w3.org/1999/02/22-rdf-syntax-ns#type"),
                                ox.NamedNode("http://www.w3.org/2002/07/owl#FunctionalProperty")))
    live = LiveKB(kb, "Robot1.1", wall_ms=wall_ms)
    for value in ("red", "blue"):
        live.update(f'INSERT DATA {{ <http://www.tcs.org/2018/Location#Pallet_9> <{colour}> "{value}" }}')
    query = f"SELECT ?c WHERE {{ ?p <{colour}> ?c }}"
    assert [str(row[0]) for row in expect_select(live.query(query), query).rows] == ["blue"]
