"""A robot's KB resources over CoAP/UDP, end to end.

The server is ``coapkb serve`` in its own OS process on 127.0.0.1; the client
is coapkb's own :class:`~coapkb.transport.coap.CoapClientTransport` (aiocoap)
with :class:`~coapkb.kb.client.KBClient`, plus a raw UDP socket for garbage.
Every wait is on the thing itself (a response, a line, a process exit).
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import os
import random
import re
import socket
import struct
from collections.abc import AsyncIterator
from decimal import Decimal

import aiocoap
import aiocoap.error
import cbor2
import pytest
import pytest_asyncio
from rdflib import Literal, URIRef
from support import GRIPPING_ROBOTS, KB_FILES, ServerProcess, free_tcp_port, free_udp_port, varied_query

from coapkb.kb.client import KBClient, QueryFailed, decode
from coapkb.kb.named_queries import NAMED_QUERIES, named_queries_for
from coapkb.kb.store import KnowledgeBase
from coapkb.model.results import SelectResult
from coapkb.transport import Endpoint, open_client
from coapkb.transport.base import ClientTransport
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status
from coapkb.transport.registry import parse_endpoint
from coapkb.wire import codec

pytestmark = pytest.mark.asyncio(loop_scope="module")


OBJ = "http://www.tcs.org/2018/Object#"
LOC = "http://www.tcs.org/2018/Location#"
CAP = "http://www.tcs.org/2018/Capability#"

#: The seed's Query_1..Query_4 with the parameters of its example task.
SEED_QUERIES = {
    "object-exists": {"name": "Gucci_bag_14"},
    "object-location": {"name": "Gucci_bag_14"},
    "object-features": {"name": "Gucci_bag_14"},
    "robots-for-grip": {"grip": "gripping"},
}


#: Takes minutes to evaluate (27k^3 solutions to count), inside one next() the
#: KB's deadline cannot interrupt: only the server's outer timeout answers.
COSTLY = "SELECT (COUNT(*) AS ?n) WHERE { ?a ?b ?c . ?d ?e ?f . ?g ?h ?i }"

GOOD = Request(Method.GET, "/kb/q/object-exists", {"name": "Gucci_bag_14"})


def check_seed_answer(name: str, result: SelectResult) -> None:
    """The facts of the seed's example task (Fig. 4)."""
    assert isinstance(result, SelectResult)
    assert not result.truncated
    rows = result.as_dicts()
    if name == "object-exists":
        assert rows == [{"object": URIRef(OBJ + "Gucci_bag_14"), "class": URIRef(OBJ + "PersonalItems")}]
    elif name == "object-location":
        [row] = rows
        assert row["loc"] == URIRef(LOC + "Warehouse_A")
        assert row["warehouse"] == Literal("Warehouse_A")
        assert (row["aisle_no"].toPython(), row["rack_no"].toPython(), row["bin_no"].toPython()) == (3, 21, 3)
    elif name == "object-features":
        [row] = rows
        assert row["grip"] == URIRef(OBJ + "gripping")
        assert row["weight"].toPython() == Decimal("0.8")
    elif name == "robots-for-grip":
        assert [str(r["robo_id"]) for r in rows] == list(GRIPPING_ROBOTS)  # ORDER BY ?robo_id
        assert {str(r["robo_id"]): r["payload"].toPython() for r in rows} == GRIPPING_ROBOTS
        assert all(r["robots"] == URIRef(CAP + str(r["robo_id"])) for r in rows)
    else:  # pragma: no cover
        raise AssertionError(name)


# --------------------------------------------------------------------------- fixtures


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def server() -> AsyncIterator[ServerProcess]:
    """One robot serving the three warehouse KBs for the whole module.

    Its stderr is drained into ``server.log`` as it comes (a full pipe would
    block the server), and checked at the end: no traceback, whatever the
    tests threw at it."""
    port = free_udp_port()
    srv = await ServerProcess.start("--kb", *KB_FILES, "--bind", f"127.0.0.1:{port}")
    srv.log = bytearray()  # type: ignore[attr-defined]
    drain = asyncio.create_task(_drain(srv))
    yield srv
    assert srv.proc.returncode is None, "the server died during the tests"
    await srv.stop()
    await drain
    log = srv.log.decode(errors="replace")  # type: ignore[attr-defined]
    assert "Traceback" not in log, log


async def _drain(srv: ServerProcess) -> None:
    assert srv.proc.stderr is not None
    while chunk := await srv.proc.stderr.read(65536):
        srv.log.extend(chunk)  # type: ignore[attr-defined]


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def transport() -> AsyncIterator[ClientTransport]:
    """A client through the reliability layer (NON tries, block by block)."""
    t = await open_client("coap")
    yield t
    await t.aclose()


@pytest.fixture
def peer(server: ServerProcess) -> Endpoint:
    return parse_endpoint(server.uri)


@pytest.fixture
def client(transport: ClientTransport) -> KBClient:
    return KBClient(transport, timeout=15)


async def call(transport: ClientTransport, peer: Endpoint, request: Request, timeout: float = 15) -> Response:
    return await transport.request(peer, request, timeout=timeout)


async def assert_healthy(client: KBClient, peer: Endpoint, server: ServerProcess) -> None:
    """The server process is alive and still answers a good query (a stuck one times out)."""
    assert server.proc.returncode is None
    result = await client.named(peer, "object-exists", {"name": "Gucci_bag_14"}, timeout=30)
    check_seed_answer("object-exists", result)


def parse_link_format(text: str) -> dict[str, dict[str, str | None]]:
    """RFC 6690 link-format: {target: {attribute: value}} (titles may hold commas)."""
    links: dict[str, dict[str, str | None]] = {}
    pos = 0
    link = re.compile(r'<([^>]*)>((?:;[^;,=]+(?:="[^"]*"|=[^;,]*)?)*)')
    attr = re.compile(r';([^;,=]+)(?:="([^"]*)"|=([^;,]*))?')
    while pos < len(text):
        m = link.match(text, pos)
        assert m is not None, f"not link-format at {pos}: {text[pos:pos + 60]!r}"
        links[m.group(1)] = {a.group(1): a.group(2) if a.group(2) is not None else a.group(3)
                             for a in attr.finditer(m.group(2))}
        pos = m.end()
        if pos < len(text):
            assert text[pos] == ",", text[pos:pos + 60]
            pos += 1
    return links


# --------------------------------------------------------------------------- discovery and /kb


async def test_well_known_core_lists_every_resource(transport: ClientTransport, peer: Endpoint) -> None:
    response = await call(transport, peer, Request(Method.GET, "/.well-known/core"))
    assert response.status == Status.CONTENT
    assert response.content_format == ContentFormat.LINK_FORMAT
    links = parse_link_format(response.text())
    assert links["/kb"]["ct"] == "60 50"
    assert links["/kb/sparql"]["rt"] == "sparql"
    assert links["/kb/sparql"]["ct"] == "60 50"
    named = {path for path, attrs in links.items() if attrs.get("rt") == "coapkb.q"}
    expected = {f"/kb/q/{q.name}" for q in named_queries_for(["Object", "Location", "Capability"])}
    assert named == expected
    assert set(SEED_QUERIES) <= {p.rsplit("/", 1)[1] for p in named}
    for path in named:
        assert links[path]["ct"] == "60 50", path
    # a parameterised query says which parameters it takes
    assert "?grip=" in (links["/kb/q/robots-for-grip"]["title"] or "")


async def test_well_known_core_rt_filter(transport: ClientTransport, peer: Endpoint) -> None:
    response = await call(transport, peer, Request(Method.GET, "/.well-known/core", {"rt": "sparql"}))
    assert response.status == Status.CONTENT
    links = parse_link_format(response.text())
    assert list(links) == ["/kb/sparql"]
    assert links["/kb/sparql"]["rt"] == "sparql"

    response = await call(transport, peer, Request(Method.GET, "/.well-known/core", {"rt": "coapkb.q"}))
    links = parse_link_format(response.text())
    assert set(links) == {f"/kb/q/{q}" for q in NAMED_QUERIES}
    assert all(a["rt"] == "coapkb.q" for a in links.values())


async def test_kb_summary(transport: ClientTransport, peer: Endpoint) -> None:
    response = await call(transport, peer, Request(Method.GET, "/kb"))
    assert response.status == Status.CONTENT
    assert response.content_format == ContentFormat.CBOR
    assert response.etag is not None and len(response.etag) >= 1
    info = cbor2.loads(response.payload)
    assert info["names"] == ["Object", "Location", "Capability"]
    assert isinstance(info["triples"], int) and info["triples"] > 1000
    assert isinstance(info["prefixes"], dict) and info["prefixes"]
    assert bytes.fromhex(info["etag"]) == response.etag
    assert set(SEED_QUERIES) <= set(info["queries"])
    assert info["queries"]["robots-for-grip"] == ["grip"]

    as_json = await call(transport, peer, Request(Method.GET, "/kb", accept=ContentFormat.JSON))
    assert as_json.content_format == ContentFormat.JSON
    assert json.loads(as_json.payload) == info
    assert as_json.etag == response.etag  # the KB's ETag, whatever the format


# --------------------------------------------------------------------------- the seed's queries


@pytest.mark.parametrize("name", list(SEED_QUERIES))
async def test_named_query_cbor_and_json(client: KBClient, peer: Endpoint, name: str) -> None:
    params = SEED_QUERIES[name]
    as_cbor = await client.named(peer, name, params, accept=ContentFormat.CBOR)
    as_json = await client.named(peer, name, params, accept=ContentFormat.JSON)
    check_seed_answer(name, as_cbor)
    assert as_json == as_cbor


@pytest.mark.parametrize("method", [Method.FETCH, Method.POST, Method.GET])
@pytest.mark.parametrize("name", list(SEED_QUERIES))
async def test_sparql_text_matches_named_query(client: KBClient, peer: Endpoint, name: str, method: Method) -> None:
    text = NAMED_QUERIES[name].render(SEED_QUERIES[name])
    named = await client.named(peer, name, SEED_QUERIES[name])
    for accept in (ContentFormat.CBOR, ContentFormat.JSON):
        result = await client.sparql(peer, text, accept=accept, method=method)
        check_seed_answer(name, result)
        assert result == named, (method, accept)


async def test_wire_formats_are_what_they_claim(transport: ClientTransport, peer: Endpoint) -> None:
    """CBOR is compact CBOR (decodable by cbor2), JSON is W3C SPARQL-JSON."""
    request = Request(Method.GET, "/kb/q/robots-for-grip", {"grip": "gripping"})
    cbor_resp = await call(transport, peer, request)
    assert cbor_resp.content_format == ContentFormat.CBOR
    cbor2.loads(cbor_resp.payload)  # well-formed CBOR
    json_resp = await call(transport, peer, Request(**{**vars(request), "accept": ContentFormat.JSON}))
    assert json_resp.content_format == ContentFormat.JSON
    doc = json.loads(json_resp.payload)
    assert doc["head"]["vars"] == ["robots", "robo_id", "payload"]
    payloads = [b["payload"] for b in doc["results"]["bindings"]]
    assert [Decimal(p["value"]) for p in payloads] == list(GRIPPING_ROBOTS.values())
    assert {p["type"] for p in payloads} == {"literal"}
    assert len(cbor_resp.payload) < len(json_resp.payload)
    assert codec.decode_cbor(cbor_resp.payload) == codec.decode_json(json_resp.payload)


async def test_named_query_cacheable(transport: ClientTransport, peer: Endpoint) -> None:
    request = Request(Method.GET, "/kb/q/object-location", {"name": "Gucci_bag_14"})
    first = await call(transport, peer, request)
    second = await call(transport, peer, request)
    assert first.status == second.status == Status.CONTENT
    assert first.max_age is not None and first.max_age > 0
    assert first.etag is not None
    assert second.etag == first.etag
    assert second.payload == first.payload
    # a different representation has a different ETag
    as_json = await call(transport, peer, Request(**{**vars(request), "accept": ContentFormat.JSON}))
    assert as_json.etag is not None and as_json.etag != first.etag
    other = await call(transport, peer, Request(Method.GET, "/kb/q/object-location", {"name": "Gucci_bag_15"}))
    assert other.status == Status.CONTENT and other.etag != first.etag


# --------------------------------------------------------------------------- errors


async def expect_error(
    transport: ClientTransport, peer: Endpoint, request: Request, status: Status, timeout: float = 15
) -> Response:
    response = await call(transport, peer, request, timeout)
    assert response.status == status, (response.status, response.text())
    return response


def fetch(text: str | bytes, **kwargs) -> Request:
    payload = text.encode() if isinstance(text, str) else text
    kwargs.setdefault("content_format", ContentFormat.TEXT)
    return Request(Method.FETCH, "/kb/sparql", payload=payload, **kwargs)


async def test_malformed_sparql_is_400_with_position(
    transport: ClientTransport, client: KBClient, peer: Endpoint, server: ServerProcess
) -> None:
    text = "PREFIX o: <http://www.tcs.org/2018/Object#>\nSELECT ?x WHERE { ?x o:weight }"
    response = await expect_error(transport, peer, fetch(text), Status.BAD_REQUEST)
    assert response.content_format == ContentFormat.TEXT
    assert re.search(r"line 2\b.*column \d+", response.text()), response.text()
    # and KBClient turns it into QueryFailed carrying the diagnostic
    with pytest.raises(QueryFailed, match=r"4\.00.*line 2"):
        await client.sparql(peer, text)
    await assert_healthy(client, peer, server)


@pytest.mark.parametrize(
    "text",
    [
        'PREFIX o: <http://www.tcs.org/2018/Object#> INSERT DATA { o:x o:weight 1 }',
        'DELETE WHERE { ?s ?p ?o }',
        'CLEAR ALL',
        'LOAD <http://example.org/kb.ttl>',
    ],
)
async def test_sparql_update_is_403(
    transport: ClientTransport, client: KBClient, peer: Endpoint, server: ServerProcess, text: str
) -> None:
    await expect_error(transport, peer, fetch(text), Status.FORBIDDEN)
    await expect_error(transport, peer, Request(Method.POST, "/kb/sparql", payload=text.encode()), Status.FORBIDDEN)
    await assert_healthy(client, peer, server)
    # nothing was deleted
    ask = await client.sparql(peer, "ASK { ?s ?p ?o }")
    assert ask.value is True


@pytest.mark.parametrize(
    "text",
    [
        "SELECT * WHERE { SERVICE <http://example.org/> { ?s ?p ?o } }",
        "SELECT * FROM <http://example.org/g> WHERE { ?s ?p ?o }",
    ],
)
async def test_network_fetching_features_are_403(
    transport: ClientTransport, client: KBClient, peer: Endpoint, server: ServerProcess, text: str
) -> None:
    response = await expect_error(transport, peer, fetch(text), Status.FORBIDDEN)
    assert "SERVICE" in response.text() or "FROM" in response.text()
    await assert_healthy(client, peer, server)


@pytest.mark.parametrize(
    "request_",
    [
        Request(Method.GET, "/kb/q/object-exists", {"name": "Gucci_bag_14"}, accept=41),
        Request(Method.FETCH, "/kb/sparql", payload=b"ASK {}", accept=41),
        Request(Method.GET, "/kb/sparql", {"q": "ASK {}"}, accept=0),
        Request(Method.GET, "/kb", accept=41),
    ],
    ids=["named", "fetch", "get-text", "kb"],
)
async def test_unsupported_accept_is_406(
    transport: ClientTransport, client: KBClient, peer: Endpoint, server: ServerProcess, request_: Request
) -> None:
    response = await expect_error(transport, peer, request_, Status.NOT_ACCEPTABLE)
    assert "60" in response.text() and "50" in response.text()
    await assert_healthy(client, peer, server)


async def test_oversized_query_is_413_after_blockwise_upload(
    transport: ClientTransport, client: KBClient, peer: Endpoint, server: ServerProcess
) -> None:
    """The query body goes block-wise (Block1, RFC 7959); the server reassembles
    it, then refuses it by size. 8192 bytes is the limit, inclusive."""
    def padded(size: int) -> str:
        tail = "\nASK { ?s ?p ?o }"
        return "#" + "x" * (size - 1 - len(tail)) + tail

    at_limit = padded(8192)
    assert len(at_limit.encode()) == 8192
    result = await client.sparql(peer, at_limit)  # the whole body arrived, or this would not parse
    assert result.value is True
    for method in (Method.FETCH, Method.POST):
        response = await expect_error(
            transport, peer,
            Request(method, "/kb/sparql", payload=padded(8193).encode(), content_format=ContentFormat.TEXT),
            Status.REQUEST_ENTITY_TOO_LARGE,
        )
        assert "8193" in response.text() and "8192" in response.text()
    response = await expect_error(transport, peer, fetch(padded(50_000)), Status.REQUEST_ENTITY_TOO_LARGE)
    await assert_healthy(client, peer, server)


@pytest.mark.parametrize("fmt", [ContentFormat.CBOR, ContentFormat.JSON, ContentFormat.LINK_FORMAT])
async def test_non_text_body_is_415(
    transport: ClientTransport, client: KBClient, peer: Endpoint, server: ServerProcess, fmt: ContentFormat
) -> None:
    for method in (Method.FETCH, Method.POST):
        request = Request(method, "/kb/sparql", payload=cbor2.dumps("ASK {}"), content_format=fmt)
        await expect_error(transport, peer, request, Status.UNSUPPORTED_CONTENT_FORMAT)
    await assert_healthy(client, peer, server)


async def test_other_bad_bodies_are_400(
    transport: ClientTransport, client: KBClient, peer: Endpoint, server: ServerProcess
) -> None:
    await expect_error(transport, peer, fetch(b"ASK { \xff\xfe }"), Status.BAD_REQUEST)  # not UTF-8
    await expect_error(transport, peer, fetch(b"   \n "), Status.BAD_REQUEST)  # empty
    await expect_error(transport, peer, Request(Method.GET, "/kb/sparql"), Status.BAD_REQUEST)  # no ?q=
    await assert_healthy(client, peer, server)


async def test_unknown_named_query_is_404(
    transport: ClientTransport, client: KBClient, peer: Endpoint, server: ServerProcess
) -> None:
    response = await expect_error(
        transport, peer, Request(Method.GET, "/kb/q/drop-everything", {"name": "x"}), Status.NOT_FOUND
    )
    assert "object-location" in response.text()  # the diagnostic lists the named queries
    with pytest.raises(QueryFailed, match=r"4\.04"):
        await client.named(peer, "nope")
    await assert_healthy(client, peer, server)


@pytest.mark.parametrize(
    "name, params",
    [
        ("object-exists", {}),  # missing
        ("object-exists", {"name": "Gucci_bag_14", "limit": "5"}),  # extra
        ("robots-for-grip", {"grip": "gripping", "name": "x"}),  # extra
        ("object-exists-in-class", {"name": "Gucci_bag_14"}),  # one of two missing
        ("object-exists", {"name": 'x" } ; DROP ALL ; #'}),  # closes the literal
        ("object-exists", {"name": "x\" . ?s ?p ?o . FILTER(\"a\"=\"a"}),
        ("object-location", {"name": "Gucci_bag_14> ?p ?o } #"}),  # closes the prefixed name
        ("object-location", {"name": "a b"}),
        ("robots-for-grip", {"grip": "gripping}"}),
        ("robots-for-grip", {"grip": ""}),
        ("robots-for-grip", {"grip": "x" * 200}),
        ("object-features", {"name": "Gucci_bag_14."}),
        ("object-features", {"name": "Gücci"}),
        ("robot-specs", {"x": "1"}),  # takes no parameters
    ],
)
async def test_bad_named_query_parameters_are_400(
    transport: ClientTransport, client: KBClient, peer: Endpoint, server: ServerProcess, name: str, params: dict
) -> None:
    response = await expect_error(transport, peer, Request(Method.GET, f"/kb/q/{name}", params), Status.BAD_REQUEST)
    assert name in response.text()
    await assert_healthy(client, peer, server)


async def test_unknown_path_is_404_and_wrong_method_405(
    transport: ClientTransport, client: KBClient, peer: Endpoint, server: ServerProcess
) -> None:
    for path in ("/nothing", "/kb/sparql/extra", "/kb/q", "/kb/query"):
        await expect_error(transport, peer, Request(Method.GET, path), Status.NOT_FOUND)
    await expect_error(transport, peer, Request(Method.DELETE, "/kb/sparql"), Status.METHOD_NOT_ALLOWED)
    await expect_error(transport, peer, Request(Method.PUT, "/kb/sparql", payload=b"ASK {}"), Status.METHOD_NOT_ALLOWED)
    await expect_error(transport, peer, Request(Method.DELETE, "/kb"), Status.METHOD_NOT_ALLOWED)
    await expect_error(
        transport, peer, Request(Method.FETCH, "/kb/q/object-exists", {"name": "Gucci_bag_14"}, payload=b"x"),
        Status.METHOD_NOT_ALLOWED,
    )
    await assert_healthy(client, peer, server)


async def test_body_hash_mismatch_is_400(transport: ClientTransport, peer: Endpoint) -> None:
    """The transport-level ``qh=`` (hash of the body) must match the body."""
    from coapkb.transport.coap import CoapClientTransport

    assert isinstance(transport, CoapClientTransport)
    msg = aiocoap.Message(code=aiocoap.FETCH, uri=f"coap://{peer.hostport}/kb/sparql", payload=b"ASK {}")
    msg.opt.uri_query = ("qh=000000000000",)
    answer = await asyncio.wait_for(transport._ctx.request(msg).response, 10)
    assert answer.code == aiocoap.BAD_REQUEST, answer
    assert b"qh" in answer.payload


@pytest.mark.parametrize(("method", "accept", "hashed"), [
    (Method.FETCH, None, True),  # a query: its answer may come in blocks
    (Method.POST, ContentFormat.CBOR, True),  # SPARQL text or a sync, answered by representation
    (Method.POST, None, False),  # a task post: a status
    (Method.PATCH, ContentFormat.CBOR, False),  # a write: its answer is a few bytes of CBOR
    (Method.IPATCH, ContentFormat.CBOR, False),
])
async def test_the_body_hash_rides_only_where_the_answer_may_come_in_blocks(method: Method, accept: int | None,
                                                                      hashed: bool) -> None:
    from coapkb.transport.coap.mapping import BODY_HASH_PARAM, message_from_request

    request = Request(method, "/kb", {"wid": "Robot1.7.1"}, payload=b"body", accept=accept)
    query = message_from_request(Endpoint("coap", "127.0.0.1", 5683), request).opt.uri_query
    assert any(q.startswith(f"{BODY_HASH_PARAM}=") for q in query) == hashed, query
    assert "wid=Robot1.7.1" in query


# --------------------------------------------------------------------------- block-wise


async def test_blockwise_result(client: KBClient, transport: ClientTransport, peer: Endpoint) -> None:
    text = "SELECT * WHERE { ?s ?p ?o } LIMIT 200"
    response = await call(transport, peer, fetch(text, accept=ContentFormat.JSON))
    assert response.status == Status.CONTENT
    assert len(response.payload) > 1024  # more than one block
    doc = json.loads(response.payload)
    assert len(doc["results"]["bindings"]) == 200
    as_json = decode(response)
    as_cbor = await client.sparql(peer, text, accept=ContentFormat.CBOR)
    assert len(as_json.rows) == 200
    assert as_cbor == as_json


def large_query(i: int) -> str:
    # different text, different answers, each over 1 KiB in either format
    return f"SELECT ?s ?p ?o WHERE {{ ?s ?p ?o }} OFFSET {i * 80} LIMIT 80"


@pytest.mark.parametrize("method", [Method.FETCH, Method.POST, Method.GET])
async def test_concurrent_blockwise_answers_do_not_mix(client: KBClient, peer: Endpoint, method: Method) -> None:
    """aiocoap's Block2 cache keys on the request options, not the body: two
    concurrent FETCHes with different queries from one client must each still
    get their own multi-block answer."""
    queries = [large_query(i) for i in range(8)]
    alone = {}
    for accept in (ContentFormat.JSON, ContentFormat.CBOR):
        for q in queries:
            if method == Method.GET:
                request = Request(method, "/kb/sparql", {"q": q}, accept=accept)
            else:
                request = Request(method, "/kb/sparql", payload=q.encode(), content_format=0, accept=accept)
            response = await client.call(peer, request)
            assert len(response.payload) > 1024, "not multi-block: the test would prove nothing"
            alone[q, accept] = decode(response)
    assert len({alone[q, ContentFormat.JSON] for q in queries}) == len(queries)  # all different
    for accept in (ContentFormat.JSON, ContentFormat.CBOR):
        for _ in range(3):
            together = await asyncio.gather(*(client.sparql(peer, q, accept=accept, method=method) for q in queries))
            for q, result in zip(queries, together):
                assert result == alone[q, accept], q
                assert len(result.rows) == 80


async def test_concurrent_mixed_formats_same_query(client: KBClient, peer: Endpoint) -> None:
    q = large_query(1)
    cbor_alone = await client.sparql(peer, q, accept=ContentFormat.CBOR)
    results = await asyncio.gather(
        *(client.sparql(peer, q, accept=a) for a in [ContentFormat.CBOR, ContentFormat.JSON] * 4)
    )
    assert all(r == cbor_alone for r in results)


# --------------------------------------------------------------------------- garbage


def _options(*options: tuple[int, bytes]) -> bytes:
    """CoAP options (number, value), encoded with extended deltas and lengths."""
    out, last = bytearray(), 0
    for number, value in sorted(options, key=lambda o: o[0]):
        parts = []
        for n in (number - last, len(value)):
            parts.append((n, b"") if n < 13 else (13, bytes([n - 13])) if n < 269 else (14, struct.pack("!H", n - 269)))
        (d, dext), (l, lext) = parts
        out += bytes([d << 4 | l]) + dext + lext + value
        last = number
    return bytes(out)


URI_PATH, CONTENT_FORMAT, URI_QUERY, ACCEPT, BLOCK2, BLOCK1 = 11, 12, 15, 17, 23, 27


def _garbage(rng: random.Random) -> list[bytes]:
    """200 datagrams: random bytes, and CoAP-looking messages with broken parts."""
    def header(mtype: int = 0, tkl: int = 2, code: int = 1) -> bytes:
        return bytes([0x40 | mtype << 4 | tkl, code]) + rng.randbytes(2) + rng.randbytes(min(tkl, 8))

    def path(*segments: str | bytes) -> list[tuple[int, bytes]]:
        return [(URI_PATH, s if isinstance(s, bytes) else s.encode()) for s in segments]

    sparql = path("kb", "sparql")
    shapes = [
        lambda: rng.randbytes(rng.randrange(0, 300)),  # noise
        lambda: rng.randbytes(rng.randrange(0, 300)),
        lambda: b"",
        lambda: bytes([0x40]),  # truncated header
        lambda: bytes([0x80]) + rng.randbytes(10),  # CoAP version 2
        lambda: header(tkl=rng.randrange(9, 16)),  # reserved token lengths
        lambda: header() + bytes([0xF0]),  # option delta 15 (reserved)
        lambda: header() + bytes([0x0F]),  # option length 15 (reserved)
        lambda: header() + bytes([0xD0]),  # extended delta, its byte missing
        lambda: header() + bytes([0xE0, 0x00]),  # 2-byte extended delta, one byte there
        lambda: header() + bytes([0xB5]) + b"ab",  # option shorter than its length
        lambda: header() + b"\xff",  # payload marker, no payload
        lambda: header() + _options(*sparql, (25, b"x")),  # unknown critical option
        lambda: header() + _options(*path("kb", b"\xff\xfe")),  # Uri-Path not UTF-8
        lambda: header() + _options(*path("kb", "q", "object-exists"), (URI_QUERY, b"name=\xc3")),  # bad UTF-8
        lambda: header(code=5) + _options(*sparql, (CONTENT_FORMAT, b"\x00" * 5)) + b"\xffASK {}",  # uint too long
        lambda: header(code=5) + _options(*sparql, (ACCEPT, b"\xff\xff\xff\xff")) + b"\xffASK {}",
        lambda: header(code=5) + _options(*sparql, (CONTENT_FORMAT, b"\x3c")) + b"\xff\xa1\x00\x00",  # CBOR body
        lambda: header(code=5) + _options(*sparql) + b"\xff" + rng.randbytes(50),  # body not UTF-8
        lambda: header(code=5) + _options(*sparql) + b"\xffSELECT * WHERE { ?s ?p",  # malformed SPARQL
        lambda: header(code=5) + _options(*sparql, (BLOCK1, b"\xff\xff\x5a")) + b"\xff" + b"x" * 64,  # no start: 4.08
        lambda: header(code=1) + _options(*sparql, (BLOCK2, b"\x0f")),  # Block2 szx 7 (reserved)
        lambda: header(code=1) + _options(*sparql, (BLOCK2, b"\x7f\xff\xf2")),  # Block2 far past the end
        lambda: header(code=rng.choice([7, 8, 30, 31])) + _options(*sparql),  # unknown methods
        lambda: header(code=0x45) + rng.randbytes(10),  # a response, sent to a server
        lambda: header(code=0xE0) + rng.randbytes(10),  # class 7 (reserved)
        lambda: header(tkl=0, code=0),  # CoAP ping (CON empty): RST
        lambda: header(tkl=4, code=0),  # empty message with a token: format error
        lambda: header(mtype=2, tkl=0, code=0),  # ACK for nothing
        lambda: header(mtype=3, tkl=0, code=0),  # RST for nothing
        lambda: header(mtype=1) + _options(*path("kb", "q", "nope")),  # NON request
        lambda: header() + _options(*path("kb", "q", "object-exists"), (URI_QUERY, b"name=" + b"A" * 300)),
        lambda: header() + _options(*path(*(["x"] * 40))),
        lambda: header() + _options((URI_PATH, rng.randbytes(rng.randrange(1, 12))), (URI_QUERY, rng.randbytes(8))),
    ]
    return [rng.choice(shapes)() for _ in range(200)]


async def test_garbage_datagrams() -> None:
    """200 broken datagrams: the server survives, keeps answering, logs little."""
    port = free_udp_port()
    srv = await ServerProcess.start("--kb", *KB_FILES, "--bind", f"127.0.0.1:{port}")
    transport = await open_client("coap")
    try:
        client = KBClient(transport, timeout=10)
        peer = parse_endpoint(srv.uri)
        check_seed_answer("robots-for-grip", await client.named(peer, "robots-for-grip", {"grip": "gripping"}))
        rng = random.Random(7252)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setblocking(False)
        try:
            for datagram in _garbage(rng):
                sock.sendto(datagram, ("127.0.0.1", port))
            # the server answers the well-formed part of the garbage (4.xx, RST)
            # and ignores the rest; a good query after it all proves it is through
            await assert_healthy(client, peer, srv)
            check_seed_answer("robots-for-grip", await client.named(peer, "robots-for-grip", {"grip": "gripping"}))
            replies = 0
            while True:
                try:
                    sock.recv(2048)
                    replies += 1
                except BlockingIOError:
                    break
            assert replies > 0  # RSTs, 4.00s, 4.02s, 4.05s... for the parsable part
        finally:
            sock.close()
        assert srv.proc.returncode is None
    finally:
        await transport.aclose()
        code = await srv.stop()
    stderr = (await srv.proc.stderr.read()).decode(errors="replace")
    assert code == 0, stderr
    assert "Traceback" not in stderr, stderr
    lines = stderr.splitlines()
    assert len(lines) < 20, "\n".join(lines)


def _block1_fetch(mid: int, block1: bytes, payload: bytes) -> bytes:
    """CON FETCH /kb/sparql (text/plain) with a Block1 option, token 0xB1."""
    return (bytes([0x41, 0x05]) + struct.pack("!H", mid) + b"\xb1"
            + _options((URI_PATH, b"kb"), (URI_PATH, b"sparql"), (CONTENT_FORMAT, b""), (BLOCK1, block1))
            + b"\xff" + payload)


async def test_block1_gap_is_408_without_a_traceback() -> None:
    port = free_udp_port()
    srv = await ServerProcess.start("--kb", *KB_FILES, "--bind", f"127.0.0.1:{port}")
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.settimeout(5)
    try:
        sock.connect(("127.0.0.1", port))
        sock.send(_block1_fetch(1, bytes([0x0A]), b"#" * 64))  # block 0, more, 64 bytes
        first = await asyncio.to_thread(sock.recv, 2048)
        assert first[1] == 0x5F  # 2.31 Continue
        sock.send(_block1_fetch(2, bytes([0x52]), b"ASK {}"))  # block 5, last: a gap
        second = await asyncio.to_thread(sock.recv, 2048)
        code = f"{second[1] >> 5}.{second[1] & 0x1F:02d}"
    finally:
        sock.close()
        await srv.stop()
    stderr = (await srv.proc.stderr.read()).decode(errors="replace")
    assert (code, "Traceback" in stderr) == ("4.08", False), stderr


# --------------------------------------------------------------------------- limits


async def test_row_limit_marks_truncated() -> None:
    port = free_udp_port()
    srv = await ServerProcess.start("--kb", *KB_FILES, "--bind", f"127.0.0.1:{port}", "--row-limit", "5")
    transport = await open_client("coap")
    try:
        client = KBClient(transport, timeout=10)
        peer = parse_endpoint(srv.uri)
        for accept in (ContentFormat.CBOR, ContentFormat.JSON):
            result = await client.sparql(peer, "SELECT * WHERE { ?s ?p ?o }", accept=accept)
            assert result.truncated is True
            assert len(result.rows) == 5
            exact = await client.sparql(peer, "SELECT * WHERE { ?s ?p ?o } LIMIT 5", accept=accept)
            assert exact.truncated is False and len(exact.rows) == 5
        # CONSTRUCT is bounded too
        graph = await client.sparql(peer, "CONSTRUCT WHERE { ?s ?p ?o }")
        assert graph.truncated is True and len(graph.triples) == 5
        # the seed's queries fit (6 robots > 5 rows: Query_4 is cut and says so)
        grip = await client.named(peer, "robots-for-grip", {"grip": "gripping"})
        assert grip.truncated is True and len(grip.rows) == 5
    finally:
        await transport.aclose()
        assert await srv.stop() == 0


async def _stop_quickly(srv: ServerProcess, grace: float) -> int:
    """SIGTERM, then SIGKILL after ``grace`` seconds: the exit code (-9 when killed)."""
    if srv.proc.returncode is None:
        srv.proc.terminate()
    try:
        code = await asyncio.wait_for(srv.proc.wait(), grace)
    except TimeoutError:
        srv.proc.kill()
        code = await srv.proc.wait()
    return code


async def test_time_budget_is_503_with_max_age() -> None:
    port = free_udp_port()
    srv = await ServerProcess.start("--kb", *KB_FILES, "--bind", f"127.0.0.1:{port}", "--time-budget", "0.05")
    transport = await open_client("coap")
    try:
        client = KBClient(transport, timeout=10)
        peer = parse_endpoint(srv.uri)
        # answered at the budget: the count itself would take minutes, and a finished one is 2.05
        response = await call(transport, peer, fetch(COSTLY), timeout=60)
        assert response.status == Status.SERVICE_UNAVAILABLE, response.text()
        assert response.max_age is not None and response.max_age >= 1
        assert "budget" in response.text()
        with pytest.raises(QueryFailed, match=r"5\.03"):
            await client.sparql(peer, COSTLY.replace("?i }", "?i . ?j ?k ?l }"))
        # the runaway worker does not stop the server answering others
        await assert_healthy(client, peer, srv)
    finally:
        await transport.aclose()
        await _stop_quickly(srv, 1)


async def test_server_stops_promptly_after_a_runaway_query() -> None:
    port = free_udp_port()
    srv = await ServerProcess.start("--kb", *KB_FILES, "--bind", f"127.0.0.1:{port}", "--time-budget", "0.05")
    transport = await open_client("coap")
    try:
        response = await call(transport, parse_endpoint(srv.uri), fetch(COSTLY), timeout=10)
        assert response.status == Status.SERVICE_UNAVAILABLE
    finally:
        await transport.aclose()
        code = await _stop_quickly(srv, 30)  # the runaway count would take minutes
    assert code == 0  # exited on SIGTERM, not killed


async def test_runaway_queries_do_not_starve_the_robot() -> None:
    port = free_udp_port()
    srv = await ServerProcess.start("--kb", *KB_FILES, "--bind", f"127.0.0.1:{port}", "--time-budget", "0.05")
    transport = await open_client("coap")
    try:
        peer = parse_endpoint(srv.uri)
        # one more than the default executor's workers; different texts so nothing is shared
        workers = min(32, (os.cpu_count() or 1) + 4)
        answers = await asyncio.gather(*(call(transport, peer, fetch(COSTLY + " " * i)) for i in range(workers + 1)))
        assert {a.status for a in answers} == {Status.SERVICE_UNAVAILABLE}
        await assert_healthy(KBClient(transport, timeout=10), peer, srv)
    finally:
        await transport.aclose()
        srv.proc.kill()
        await srv.proc.wait()


# --------------------------------------------------------------------------- the port


async def test_second_server_on_same_port_fails_clearly(server: ServerProcess) -> None:
    port = parse_endpoint(server.uri).port
    import sys

    from support import ROOT

    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "coapkb", "serve", "--kb", *KB_FILES, "--bind", f"127.0.0.1:{port}",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, cwd=ROOT,
    )
    out, err = await asyncio.wait_for(proc.communicate(), 30)
    assert proc.returncode != 0
    text = err.decode()
    assert "Traceback" not in text, text
    lines = [line for line in text.splitlines() if line.strip()]
    assert len(lines) == 1, text
    assert lines[0].startswith("coapkb: ") and str(port) in lines[0] and "in use" in lines[0], lines
    assert not out.strip()
    assert server.proc.returncode is None  # the first server is unharmed


# --------------------------------------------------------------------------- ZeroMQ


async def test_zmq_transport_answers_identically(client: KBClient, peer: Endpoint) -> None:
    port = free_tcp_port()
    srv = await ServerProcess.start("--kb", *KB_FILES, "--transport", "zmq", "--bind", f"127.0.0.1:{port}")
    zmq_transport = await open_client("zmq")
    try:
        zmq_peer = parse_endpoint(srv.uri)
        assert zmq_peer.scheme == "zmq" and zmq_peer.port == port
        zmq_client = KBClient(zmq_transport, timeout=10)
        for name, params in SEED_QUERIES.items():
            for accept in (ContentFormat.CBOR, ContentFormat.JSON):
                over_coap = await client.named(peer, name, params, accept=accept)
                over_zmq = await zmq_client.named(zmq_peer, name, params, accept=accept)
                check_seed_answer(name, over_zmq)
                assert over_zmq == over_coap, (name, accept)
            text = NAMED_QUERIES[name].render(params)
            assert await zmq_client.sparql(zmq_peer, text) == await client.sparql(peer, text)
        with pytest.raises(QueryFailed, match=r"4\.00"):
            await zmq_client.sparql(zmq_peer, "SELECT WHERE")
    finally:
        await zmq_transport.aclose()
        assert await srv.stop() == 0


async def test_etag_validation_answers_203_without_payload(transport: ClientTransport, peer: Endpoint) -> None:
    request = Request(Method.GET, "/kb/q/object-exists", {"name": "Gucci_bag_14"}, accept=ContentFormat.CBOR)
    first = await call(transport, peer, request)
    assert first.status == Status.CONTENT and first.etag
    again = await call(transport, peer, dataclasses.replace(request, etags=(b"stale!!!", first.etag)))
    assert again.status == Status.VALID and again.payload == b"" and again.etag == first.etag
    other = await call(transport, peer, dataclasses.replace(request, etags=(b"stale!!!",)))
    assert other.status == Status.CONTENT and other.payload == first.payload


async def test_client_cache_serves_fresh_answers_and_revalidates_stale_ones(
    transport: ClientTransport, peer: Endpoint
) -> None:
    now = [1000.0]
    client = KBClient(transport, timeout=10, cache=True, clock=lambda: now[0])
    sent = transport.counters.messages_sent
    first = await client.named(peer, "object-location", {"name": "Gucci_bag_14"})
    assert transport.counters.messages_sent > sent
    sent = transport.counters.messages_sent
    assert await client.named(peer, "object-location", {"name": "Gucci_bag_14"}) == first
    assert transport.counters.messages_sent == sent  # fresh: no traffic at all
    now[0] += 10_000  # past Max-Age: revalidate with the ETag, 2.03 Valid
    received = transport.counters.bytes_received
    assert await client.named(peer, "object-location", {"name": "Gucci_bag_14"}) == first
    assert transport.counters.bytes_received - received < 30  # no payload came back
    assert (client.cache_stats.hits, client.cache_stats.revalidated, client.cache_stats.misses) == (1, 1, 1)


async def test_client_cache_keeps_its_most_recently_used_answers_only(
    transport: ClientTransport, peer: Endpoint
) -> None:
    client = KBClient(transport, timeout=10, cache=True, cache_entries=2)
    for name in ("Gucci_bag_14", "Gucci_bag_1", "Gucci_bag_14", "Gucci_bag_2"):
        await client.named(peer, "object-location", {"name": name})
    # Gucci_bag_1 was the least recently used when a third answer came.
    assert (client.cache_stats.hits, client.cache_stats.misses) == (1, 3)
    sent = transport.counters.messages_sent
    await client.named(peer, "object-location", {"name": "Gucci_bag_14"})
    assert transport.counters.messages_sent == sent
    await client.named(peer, "object-location", {"name": "Gucci_bag_1"})
    assert transport.counters.messages_sent > sent and client.cache_stats.misses == 4


# --------------------------------------------------------------------------- block-wise with aiocoap's own client


@pytest.fixture(scope="module")
def local_kb() -> KnowledgeBase:
    """The server's KBs, loaded here: every answer is compared with the KB's own result."""
    return KnowledgeBase.load(KB_FILES)


def aiocoap_query(peer: Endpoint, text: str, method: aiocoap.Code = aiocoap.FETCH,
                  request_tag: bytes | None = None) -> aiocoap.Message:
    """A plain aiocoap request, as any user of aiocoap would write it (no ``qh=``)."""
    msg = aiocoap.Message(code=method, uri=f"coap://{peer.hostport}/kb/sparql", payload=text.encode(),
                          content_format=0, accept=ContentFormat.JSON)
    if request_tag is not None:
        msg.opt.request_tag = (request_tag,)
    return msg


def check_kb_answer(local_kb: KnowledgeBase, text: str, answer: aiocoap.Message) -> None:
    assert answer.code == aiocoap.CONTENT, (answer.code, answer.payload[:200])
    assert codec.decode_json(answer.payload) == local_kb.query(text), text


@pytest.mark.parametrize("method", [aiocoap.FETCH, aiocoap.POST])
async def test_aiocoap_client_large_questions_in_a_row(
    server: ServerProcess, peer: Endpoint, local_kb: KnowledgeBase, method: aiocoap.Code
) -> None:
    """aiocoap's client sends Block2 follow-ups without the body: twelve
    different multi-block questions in a row from one context each get their
    own answer (the old cache refused every one after the first with 4.08)."""
    texts = [varied_query(i) for i in range(12)]
    assert sum(len(codec.encode_json(local_kb.query(t))) > 1024 for t in texts) >= 9, "mostly multi-block"
    ctx = await aiocoap.Context.create_client_context(transports=["udp6"])
    try:
        for _ in range(2):  # and the same questions again: answers served afresh
            for text in texts:
                answer = await asyncio.wait_for(ctx.request(aiocoap_query(peer, text, method)).response, 15)
                check_kb_answer(local_kb, text, answer)
    finally:
        await ctx.shutdown()


async def test_aiocoap_clients_concurrently(server: ServerProcess, peer: Endpoint, local_kb: KnowledgeBase) -> None:
    """Eight contexts (eight client endpoints) at once, each asking in a row."""
    async def user(n: int) -> None:
        ctx = await aiocoap.Context.create_client_context(transports=["udp6"])
        try:
            for i in range(6):
                text = varied_query(n * 6 + i)
                answer = await asyncio.wait_for(ctx.request(aiocoap_query(peer, text)).response, 30)
                check_kb_answer(local_kb, text, answer)
        finally:
            await ctx.shutdown()

    await asyncio.gather(*(user(n) for n in range(8)))


async def test_request_tag_separates_concurrent_transfers(
    server: ServerProcess, peer: Endpoint, local_kb: KnowledgeBase
) -> None:
    """RFC 9175: with a Request-Tag per request, concurrent body-less transfers
    from one endpoint are each matched to their own answer."""
    texts = [varied_query(i) for i in (1, 2, 3, 4, 6, 7)]
    ctx = await aiocoap.Context.create_client_context(transports=["udp6"])
    try:
        answers = await asyncio.wait_for(asyncio.gather(*(
            ctx.request(aiocoap_query(peer, t, request_tag=bytes([n]))).response for n, t in enumerate(texts)
        )), 30)
    finally:
        await ctx.shutdown()
    for text, answer in zip(texts, answers):
        check_kb_answer(local_kb, text, answer)


async def test_untagged_concurrent_transfers_never_mix(
    server: ServerProcess, peer: Endpoint, local_kb: KnowledgeBase
) -> None:
    """Without Request-Tag or body, concurrent transfers from one endpoint are
    ambiguous.  Every block of an answer carries that answer's ETag, so
    aiocoap's client (which checks it) fails such a request rather than
    assembling two answers: each result is right or an error, never wrong."""
    texts = [varied_query(i) for i in (1, 2, 3, 4, 6, 7)]
    ctx = await aiocoap.Context.create_client_context(transports=["udp6"])
    try:
        answers = await asyncio.wait_for(asyncio.gather(
            *(ctx.request(aiocoap_query(peer, t)).response for t in texts), return_exceptions=True), 30)
    finally:
        await ctx.shutdown()
    right = 0
    for text, answer in zip(texts, answers):
        if isinstance(answer, aiocoap.Message) and answer.code == aiocoap.CONTENT:
            check_kb_answer(local_kb, text, answer)
            right += 1
        elif isinstance(answer, aiocoap.Message):
            assert answer.code == aiocoap.REQUEST_ENTITY_INCOMPLETE, answer
        else:
            assert isinstance(answer, aiocoap.error.ResourceChanged), repr(answer)
    assert right >= 1  # the newest transfer always completes
