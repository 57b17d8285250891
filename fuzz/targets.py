"""Fuzz targets: every parser that reads bytes from the network or a file.

Each target takes one input (``bytes``) and feeds it to a real parser of
coapkb.  A parser may refuse input only with its documented error (a
:class:`~coapkb.errors.CoapkbError` subclass, or what its docstring names);
any other exception escaping is a crash.  Where a decode succeeds and the
module has an encoder, the target also checks that encoding the result and
decoding it again gives the same thing back.

Inputs that carry several fields (a Zenoh query: key, parameters, payload,
...) are cut with :func:`fields`: a one-byte length before every field but
the last, which takes the rest.  The seeds in :func:`seeds` are written by
the project's own encoders, so the fuzzer starts from valid messages.
"""

from __future__ import annotations

import asyncio
import functools
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import aiocoap
import aiocoap.error
from aiocoap.numbers.codes import Code

from coapkb.agent.robot_state import Decision, LiveState, PlannedState, RobotState
from coapkb.config import ConfigError, config_from_bytes, dump_config, parse_config
from coapkb.discovery.client import DirectoryClient, DiscoveryError, registration_links
from coapkb.discovery.directory import EP_LOOKUP_PATH, REGISTER_PATH, RES_LOOKUP_PATH, DirectoryService
from coapkb.discovery.multicast import _Asker, _Responder
from coapkb.kb import update as kb_update
from coapkb.kb.named_queries import NAMED_QUERIES
from coapkb.kb.resources import KBResources
from coapkb.kb.store import KnowledgeBase
from coapkb.model.deltas import CausalContext, Delta, Dot, Stamp, WrittenState
from coapkb.model.results import AskResult, GraphResult, SelectResult
from coapkb.transport import envelope as zmq_envelope
from coapkb.transport.base import Endpoint, TransportError
from coapkb.transport.coap import mapping as coap_mapping
from coapkb.transport.coap.blockwise import BodyAwareBlock2Cache, GapSafeBlock1Spool
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status
from coapkb.transport.router import Router
from coapkb.transport.zenoh import mapping as zenoh_mapping
from coapkb.wire import codec, sync

ROOT = Path(__file__).resolve().parent.parent
ONTOLOGIES = ROOT / "ontologies"
EXAMPLE_CONFIGS = ROOT / "examples" / "three-robots"

Target = Callable[[bytes], None]
TARGETS: dict[str, Target] = {}


def target(fn: Target) -> Target:
    TARGETS[fn.__name__] = fn
    return fn


def fields(data: bytes, n: int) -> list[bytes]:
    """``n`` fields of ``data``: each but the last after a one-byte length,
    the last one the rest (missing fields are empty)."""
    out = []
    for _ in range(n - 1):
        length = data[0] if data else 0
        out.append(data[1 : 1 + length])
        data = data[1 + length :]
    out.append(data)
    return out


def pack(*parts: bytes) -> bytes:
    """The inverse of :func:`fields` (every part but the last at most 255 bytes)."""
    out = b""
    for part in parts[:-1]:
        assert len(part) < 256, part
        out += bytes([len(part)]) + part
    return out + parts[-1]


def text(data: bytes) -> str:
    # What a peer's str arrives as: Zenoh's key expressions and parameters
    # and CoAP's decoded payloads are valid Unicode.
    return data.decode("utf-8", "replace")


# --------------------------------------------------------------------------- result codecs


def _result_round_trip(result: Any) -> None:
    """Both encoders take any decoded result, and decoding gives it back."""
    assert codec.decode_cbor(codec.encode_cbor(result)) == result, result
    assert codec.decode_json(codec.encode_json(result)) == result, result


@target
def codec_cbor(data: bytes) -> None:
    try:
        result = codec.decode_cbor(data)
    except codec.CodecError:
        return
    _result_round_trip(result)


@target
def codec_json(data: bytes) -> None:
    try:
        result = codec.decode_json(data)
    except codec.CodecError:
        return
    _result_round_trip(result)


# --------------------------------------------------------------------------- ZeroMQ envelope


@target
def zmq_envelope_decode(data: bytes) -> None:
    try:
        token, request, observe = zmq_envelope.decode_request(data)
    except zmq_envelope.WireError:
        pass
    else:
        again = zmq_envelope.encode_request(request, observe=observe, token=token)
        assert zmq_envelope.decode_request(again) == (token, request, observe)
    try:
        token, response, seq = zmq_envelope.decode_response(data)
    except zmq_envelope.WireError:
        return
    again = zmq_envelope.encode_response(token, response, seq=seq)
    assert zmq_envelope.decode_response(again) == (token, response, seq)


# --------------------------------------------------------------------------- Zenoh mapping


@target
def zenoh_mapping_decode(data: bytes) -> None:
    """First byte: bit 0 reply (else query), bit 1 no attachment, bit 2 no
    encoding.  Then key, parameters, encoding, payload, attachment (fields)."""
    flags = data[0] if data else 0
    key, parameters, encoding_bytes, payload, attachment_bytes = fields(data[1:], 5)
    encoding = None if flags & 4 else text(encoding_bytes)
    attachment = None if flags & 2 else attachment_bytes
    if flags & 1:
        try:
            response, seq = zenoh_mapping.response_from_reply(payload, encoding, attachment)
        except zenoh_mapping.MappingError:
            return
        header = zenoh_mapping.ResponseHeader(response.status, response.max_age, response.etag, seq)
        again = zenoh_mapping.response_from_reply(
            response.payload,
            zenoh_mapping.encoding_for(response.content_format),
            zenoh_mapping.encode_response_header(header),
        )
        assert again == (response, seq)
        return
    try:
        request, req_header = zenoh_mapping.request_from_query(text(key), text(parameters), payload, encoding, attachment)
    except zenoh_mapping.MappingError:
        return
    try:
        key_again = zenoh_mapping.key_for_path(request.path)
    except ValueError:  # documented: a path with an empty segment has no key (the server refuses it)
        return
    again, header_again = zenoh_mapping.request_from_query(
        key_again,
        zenoh_mapping.parameters_text(request.query),
        request.payload,
        zenoh_mapping.encoding_for(request.content_format),
        zenoh_mapping.encode_request_header(req_header),
    )
    assert (again, header_again) == (request, req_header)


# --------------------------------------------------------------------------- CoAP message mapping


@target
def coap_mapping_decode(data: bytes) -> None:
    try:
        msg = aiocoap.Message.decode(data)
    except Exception:  # noqa: BLE001 - aiocoap's own decoding: not coapkb's parser
        return
    if msg.code.is_request():
        path = "/" + "/".join(msg.opt.uri_path)
        try:
            coap_mapping.request_from_message(path, msg)
        except ValueError:  # documented: an unknown method code (the server answers 4.05)
            return
    elif msg.code.is_response():
        try:
            response = coap_mapping.response_from_message(msg)
        except TransportError:  # documented: a response code coapkb has no Status for
            return
        again = coap_mapping.response_from_message(coap_mapping.message_from_response(response))
        assert again == response, (again, response)


# --------------------------------------------------------------------------- block-wise transfer


class _Remote:
    """The least of an aiocoap remote the block-wise code asks about."""

    blockwise_key = ("fuzz", 5683)
    maximum_block_size_exp = 6
    maximum_payload_size = 1024
    is_multicast_locally = False
    scheme = "coap"


def _answer_to(req: aiocoap.Message) -> aiocoap.Message:
    """A resource's answer: its size and bytes follow from the request body,
    so different bodies get different (often multi-block) answers."""
    body = req.payload
    size = 0 if not body else 700 * (body[0] % 8)
    payload = (body * (size // max(len(body), 1) + 1))[:size]
    return aiocoap.Message(code=Code.CONTENT, payload=payload, content_format=0)


async def _blockwise(messages: list[aiocoap.Message]) -> None:
    spool = GapSafeBlock1Spool()
    cache = BodyAwareBlock2Cache(max_per_key=2)

    async def build(req: aiocoap.Message) -> aiocoap.Message:
        return _answer_to(req)

    for msg in messages:
        try:
            req = spool.feed_and_take(msg)
            answer = await cache.extract_or_insert(req, functools.partial(build, req))
        except aiocoap.error.RenderableError:
            continue  # 2.31 Continue, 4.08 Incomplete, 4.00: answers aiocoap sends for us
        if answer.opt.block2 is not None:
            # Rule 4 of the module: every block of a multi-block answer names it by an ETag.
            assert answer.opt.etag is not None, answer


@target
def blockwise(data: bytes) -> None:
    """Several CoAP requests, each after a two-byte length, to one resource's
    Block1 spool and Block2 cache."""
    messages = []
    while len(data) >= 2 and len(messages) < 16:
        length = int.from_bytes(data[:2], "big")
        chunk, data = data[2 : 2 + length], data[2 + length :]
        try:
            msg = aiocoap.Message.decode(chunk, remote=_Remote())
        except Exception:  # noqa: BLE001 - aiocoap's own decoding
            continue
        if msg.code.is_request():  # only requests reach a resource
            messages.append(msg)
    if not messages:
        return
    loop = asyncio.new_event_loop()  # the caches' timers die with it
    try:
        loop.run_until_complete(_blockwise(messages))
    finally:
        loop.close()


# --------------------------------------------------------------------------- KB requests


@functools.cache
def _kb() -> tuple[Router, asyncio.AbstractEventLoop]:
    """The three ontologies behind their resources, built once."""
    kb = KnowledgeBase.load(sorted(ONTOLOGIES.glob("*.owl")))
    router = Router()
    KBResources(kb).mount(router)
    return router, asyncio.new_event_loop()


async def _handle(router: Router, request: Request) -> Response:
    # The handler itself rather than Router.handle, which would turn a
    # crash into a logged 5.00: the fuzzer should see the traceback.
    route = router._routes.get(request.path)
    if route is None or request.method not in route[0].methods:
        return await router.handle(request)
    return await route[1](request)


_ACCEPTS = (None, ContentFormat.CBOR, ContentFormat.JSON, ContentFormat.TEXT)


def kb_request_from(data: bytes) -> Request:
    """First byte: bits 0-1 the route (0 FETCH /kb/sparql with the rest as
    body, 1 GET /kb/sparql?q=rest, 2 GET /kb/q/NAME?k=v&... from the rest,
    3 POST /kb/sparql, content-format text/plain), bits 2-3 the Accept,
    bit 4 a content-format of 60 on a body (unsupported)."""
    flags = data[0] if data else 0
    rest = data[1:]
    accept = _ACCEPTS[(flags >> 2) & 3]
    route = flags & 3
    if route == 1:
        return Request(Method.GET, "/kb/sparql", {"q": text(rest)}, accept=accept)
    if route == 2:
        name, _, query = text(rest).partition("?")
        params = dict(item.partition("=")[::2] for item in query.split("&") if item)
        return Request(Method.GET, "/kb/q/" + name, params, accept=accept)
    content_format = ContentFormat.CBOR if flags & 16 else (ContentFormat.TEXT if route == 3 else None)
    method = Method.POST if route == 3 else Method.FETCH
    return Request(method, "/kb/sparql", payload=rest, content_format=content_format, accept=accept)


@target
def kb_request(data: bytes) -> None:
    router, loop = _kb()
    response = loop.run_until_complete(_handle(router, kb_request_from(data)))
    # Bad SPARQL or parameters get a 4.xx; 5.03 only for the time budget or
    # too many queries at once.  Never 5.00.
    assert response.status < 500 or response.status == Status.SERVICE_UNAVAILABLE, response
    if response.status == Status.CONTENT and response.content_format in (ContentFormat.CBOR, ContentFormat.JSON):
        decode = codec.decode_cbor if response.content_format == ContentFormat.CBOR else codec.decode_json
        decode(response.payload)  # the server's answer is one its clients can read


# --------------------------------------------------------------------------- replication and patches


@target
def sync_decode(data: bytes) -> None:
    try:
        message = sync.decode_sync(data)
    except codec.CodecError:
        return
    # Compared as bytes: the wire groups removed dots by writer, so a decoded
    # delta's order may differ from a message that split one writer's dots.
    encoded = sync.encode_sync(message)
    assert sync.encode_sync(sync.decode_sync(encoded)) == encoded


@target
def patch_decode(data: bytes) -> None:
    try:
        deletes, inserts = kb_update.decode_patch(data)
    except codec.CodecError:
        return
    encoded = kb_update.encode_patch(deletes, inserts)
    assert kb_update.encode_patch(*kb_update.decode_patch(encoded)) == encoded


# --------------------------------------------------------------------------- robot state


@target
def robot_state(data: bytes) -> None:
    try:
        state = RobotState.decode(data)
    except ValueError:  # documented: "not a robot state"
        return
    encoded = state.encode()
    # Compared as bytes: a state may hold a NaN, which equals nothing.
    assert RobotState.decode(encoded).encode() == encoded


# --------------------------------------------------------------------------- TOML configuration


@target
def config_toml(data: bytes) -> None:
    # As the contents of a robot's file beside the examples' (their relative
    # paths, ``../../ontologies/...``, resolve from there), but never written:
    # fuzzing workers end without exit handlers, and a file or folder of
    # theirs would be left behind.
    path = EXAMPLE_CONFIGS / "robot.toml"
    try:
        config = config_from_bytes(data, path)
    except ConfigError:
        return
    dumped = dump_config(config)
    again = parse_config(tomllib.loads(dumped), base_dir=path.parent)
    assert dump_config(again) == dumped


# --------------------------------------------------------------------------- link-format (discovery)


class _FakeClient:
    """A client transport whose every answer is the fuzzed payload."""

    def __init__(self, payload: bytes) -> None:
        self.payload = payload

    async def request(self, peer: Endpoint, request: Request, timeout: float | None = None) -> Response:
        return Response(Status.CONTENT, self.payload, ContentFormat.LINK_FORMAT)

    async def aclose(self) -> None:
        pass


@functools.cache
def _discovery_config() -> Any:
    data = tomllib.loads((EXAMPLE_CONFIGS / "Robot1.toml").read_text())
    del data["security"]
    data["discovery"] = {"method": "rd", "rd": "coap://127.0.0.1:5690", "cluster": "c1"}
    return parse_config(data, base_dir=EXAMPLE_CONFIGS)


class _Sink:
    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def sendto(self, data: bytes, addr: Any) -> None:
        self.sent.append(data)


ASKER_TOKEN = b"\x01\x02\x03\x04"


async def _discovery(flags: int, payload: bytes) -> None:
    kind = flags % 5
    if kind in (0, 1):  # what the directory answers a robot's lookups
        client = DirectoryClient(_discovery_config(), _FakeClient(payload))  # type: ignore[arg-type]
        try:
            if kind == 0:
                client._endpoints(Response(Status.CONTENT, payload).text())
            else:
                await client.modules()
        except DiscoveryError:
            pass
    elif kind == 2:  # a registration, then both lookups render what it registered
        service = DirectoryService(authenticated=False)
        try:
            query = {"ep": "Robot1", "d": "c1", "lt": "60", "base": "coap://127.0.0.1:5721"}
            reg = Request(Method.POST, REGISTER_PATH, query, payload, ContentFormat.LINK_FORMAT)
            for request in (
                reg,
                reg,  # a renewal compares the links
                Request(Method.GET, EP_LOOKUP_PATH, {"d": "c1"}),
                Request(Method.GET, RES_LOOKUP_PATH, {"rt": "coapkb.kb"}),
                Request(Method.GET, RES_LOOKUP_PATH, {}),
                Request(Method.GET, RES_LOOKUP_PATH, {"kb": "Obj*", "obs": "x*", "if": "y*"}),  # wildcards
                Request(Method.GET, EP_LOOKUP_PATH, {"base": "coap*", "rt": "z*"}),
            ):
                response = await _handle(service.router, request)
                assert response.status != Status.INTERNAL_SERVER_ERROR, response
        finally:
            service.close()
    elif kind == 3:  # a multicast answer to a robot looking for the directory
        asker = _Asker(ASKER_TOKEN)
        asker.datagram_received(payload, ("192.0.2.1", 5683))
    else:  # a multicast request to the directory's announcer
        responder = _Responder(Endpoint("coap", "192.0.2.2", 5683))
        responder.connection_made(_Sink())
        responder.datagram_received(payload, ("192.0.2.1", 5683))


@target
def discovery_links(data: bytes) -> None:
    """First byte modulo 5: 0 the endpoint lookup's answer, 1 the resource
    lookup's, 2 a registration's body, 3 a multicast answer (CoAP), 4 a
    multicast request (CoAP).  The rest is the payload or datagram."""
    loop = asyncio.new_event_loop()
    try:
        loop.run_until_complete(_discovery(data[0] if data else 0, data[1:]))
    finally:
        loop.close()


# --------------------------------------------------------------------------- seeds


def _results() -> list[Any]:
    from rdflib.term import BNode, Literal, URIRef

    ns = "http://www.semanticweb.org/ontologies/Object#"
    xsd = "http://www.w3.org/2001/XMLSchema#"
    rows = (
        (URIRef(ns + "Gucci_bag_14"), Literal("3.5", datatype=URIRef(xsd + "decimal")), Literal("red", lang="en")),
        (URIRef(ns + "Shoe_2"), Literal("01", datatype=URIRef(xsd + "integer")), None),
        (BNode("b0"), Literal(2.5), Literal("x", datatype=URIRef(ns + "custom"))),
        (URIRef(ns + "Box"), Literal(True), Literal("2024-01-01", datatype=URIRef(xsd + "date"))),
    )
    return [
        AskResult(True),
        SelectResult(("s", "p", "o"), rows, False),
        SelectResult(("x",), ((Literal(7),),), True),
        GraphResult(((URIRef(ns + "a"), URIRef(ns + "b"), Literal("c")),), False),
    ]


def _robot_states() -> list[RobotState]:
    plan = PlannedState(3, 4, 500.0, 1.5, 60.0, 2)
    decision = Decision(2, "Gucci_bag_14", False, "Robot1", {"Robot1": 1.5, "Robot2": None}, None, 0.25,
                        {"Robot2": "too heavy"}, 1, ("Robot1", "Robot2"), None)
    live = LiveState(3.0, 4.0, "picking", "Gucci_bag_14", 1, 2, (5, 6), "lease lost")
    return [
        RobotState("Robot1", plan, LiveState(3.0, 4.0), None, None, 0),
        RobotState("Robot2", plan, live, decision, PlannedState(1, 0, 556.0, 0.0, 60.6), 12345),
    ]


def _coap_messages() -> list[aiocoap.Message]:
    def with_ids(msg: aiocoap.Message) -> aiocoap.Message:
        msg.mtype, msg.mid, msg.token = aiocoap.CON, 7, ASKER_TOKEN
        return msg

    sparql = b"SELECT * WHERE { ?s ?p ?o } LIMIT 3"
    request = coap_mapping.message_from_request(
        Endpoint("coap", "127.0.0.1", 5683),
        Request(Method.FETCH, "/kb/sparql", {"a": "b"}, sparql, 0, 60, (b"\x01\x02",)),
    )
    get = coap_mapping.message_from_request(
        Endpoint("coap", "127.0.0.1", 5683), Request(Method.GET, "/kb/q/object-exists", {"name": "Shoe_2"}),
        observe=True,
    )
    response = coap_mapping.message_from_response(Response(Status.CONTENT, b"\xf5", 60, 300, b"\xaa\xbb"))
    error = coap_mapping.message_from_response(Response.error(Status.NOT_FOUND, "no resource at /x"))
    return [with_ids(m) for m in (request, get, response, error)]


def _block_requests() -> list[bytes]:
    """A FETCH whose answer takes blocks, its body-less Block2 follow-ups, and
    a Block1 upload in two parts."""
    def msg(payload: bytes, **options: Any) -> bytes:
        m = aiocoap.Message(code=Code.FETCH, uri_path=("kb", "sparql"), payload=payload, **options)
        m.mtype, m.mid, m.token = aiocoap.CON, 1, b"\x05"
        return m.encode()

    from aiocoap.optiontypes import BlockOption

    body = b"\x07" + b"q" * 40
    block = BlockOption.BlockwiseTuple
    first = msg(body)
    follow = [msg(b"", block2=block(n, 0, 6)) for n in (1, 2, 5)]
    upload = [msg(b"\x05" + b"u" * 15, block1=block(0, 1, 2)), msg(b"v" * 20, block1=block(1, 0, 2))]
    return [b"".join(len(m).to_bytes(2, "big") + m for m in seq) for seq in ([first, *follow], upload)]


def _sync_messages() -> list[sync.SyncMessage]:
    """A push of deltas, a whole written state, and a bare context."""
    from rdflib.term import Literal, URIRef

    loc = "http://www.tcs.org/2018/Location#"
    aisle = (URIRef(loc + "Robot1"), URIRef(loc + "Robot_aisle_no"), Literal(4))
    old = (URIRef(loc + "Robot1"), URIRef(loc + "Robot_aisle_no"), Literal(9))
    near = (URIRef(loc + "Robot1"), URIRef(loc + "near"), Literal("Rack 3", lang="en"))
    context = CausalContext({"Robot1.17": 3, "Robot2.4": 1}, [Dot("Robot2.4", 3)])
    deltas = [
        Delta(Dot("Robot1.17", 3), Stamp(1_700_000_000_000, 1, "Robot1.17"), added=(aisle,),
              removed=(Dot("Robot1.17", 2), Dot("Robot2.4", 1)), removed_base=(old,)),
        Delta(Dot("Robot2.4", 3), Stamp(1_700_000_000_005, 0, "Robot2.4"), added=(near,)),
    ]
    state = WrittenState(context, {aisle: {Dot("Robot1.17", 3): Stamp(1_700_000_000_000, 1, "Robot1.17")},
                                   near: {Dot("Robot2.4", 3): Stamp(1_700_000_000_005, 0, "Robot2.4")}},
                         frozenset({old}))
    return [sync.SyncMessage("Location", context, changes) for changes in (deltas, state, None)]


def seeds() -> dict[str, list[bytes]]:
    """A few valid inputs per target, written by the project's encoders."""
    results = _results()
    out: dict[str, list[bytes]] = {
        "codec_cbor": [codec.encode_cbor(r) for r in results],
        "codec_json": [codec.encode_json(r) for r in results],
    }
    requests = [
        Request(Method.GET, "/kb/q/object-exists", {"name": "Gucci_bag_14"}, accept=60, etags=(b"\x01" * 8,)),
        Request(Method.FETCH, "/kb/sparql", {}, b"ASK { ?s ?p ?o }", 0, 50),
    ]
    responses = [Response(Status.CONTENT, codec.encode_cbor(results[1]), 60, 300, b"\x02" * 8),
                 Response.error(Status.BAD_REQUEST, "malformed SPARQL")]
    out["zmq_envelope_decode"] = [
        zmq_envelope.encode_request(requests[0], token=1, observe=True),
        zmq_envelope.encode_request(requests[1], token=2**40),
        zmq_envelope.encode_response(1, responses[0], seq=3),
        zmq_envelope.encode_response(2, responses[1]),
    ]
    zenoh = []
    for request in requests:
        header = zenoh_mapping.RequestHeader(
            request.method, request.accept, request.etags,
            zenoh_mapping.Observe.REGISTER if request.method == Method.GET else None,
            "coapkb-obs/abc/1" if request.method == Method.GET else None,
        )
        attachment = zenoh_mapping.encode_request_header(header)
        encoding = zenoh_mapping.encoding_for(request.content_format)
        flags = (2 if attachment is None else 0) | (4 if encoding is None else 0)
        zenoh.append(bytes([flags]) + pack(
            zenoh_mapping.key_for_path(request.path).encode(),
            zenoh_mapping.parameters_text(request.query).encode(),
            (encoding or "").encode(), request.payload, attachment or b"",
        ))
    for i, response in enumerate(responses):
        attachment = zenoh_mapping.encode_response_header(
            zenoh_mapping.ResponseHeader(response.status, response.max_age, response.etag, i or None)
        )
        encoding = zenoh_mapping.encoding_for(response.content_format)
        flags = 1 | (2 if attachment is None else 0) | (4 if encoding is None else 0)
        zenoh.append(bytes([flags]) + pack(b"", b"", (encoding or "").encode(), response.payload, attachment or b""))
    out["zenoh_mapping_decode"] = zenoh
    out["coap_mapping_decode"] = [m.encode() for m in _coap_messages()]
    out["blockwise"] = _block_requests()
    queries = [
        b"\x00" + b"SELECT ?s WHERE { ?s ?p ?o } LIMIT 5",
        b"\x04" + b"PREFIX ns_1: <http://x/> ASK { ?s ns_1:Robot_Id ?o }",
        b"\x09" + b"CONSTRUCT { ?s ?p ?o } WHERE { ?s ?p ?o } LIMIT 2",
        b"\x03" + b"DESCRIBE <http://www.semanticweb.org/ontologies/Object#Shoe_2>",
        b"\x00" + b"INSERT DATA { <a:b> <a:c> <a:d> }",
        b"\x00" + b"SELECT * FROM <http://example.org/> WHERE { ?s ?p ?o }",
        b"\x00" + b"SELECT (COUNT(*) AS ?n) WHERE { ?s ?p ?o } GROUP BY ?p ORDER BY DESC(?n)",
    ]
    for name, query in sorted(NAMED_QUERIES.items()):
        params = "&".join(f"{p}={'Robot1,Robot2' if p in query.lists else 'Gucci_bag_14'}" for p in query.params)
        queries.append(b"\x02" + f"{name}?{params}".encode())
    out["kb_request"] = queries
    out["robot_state"] = [s.encode() for s in _robot_states()] + [_robot_states()[1].encode_plan()]
    messages = _sync_messages()
    out["sync_decode"] = [sync.encode_sync(m) for m in messages]
    written = messages[0].changes
    assert isinstance(written, list)
    out["patch_decode"] = [
        kb_update.encode_patch(written[0].removed_base, written[0].added),
        kb_update.encode_patch([], [t for d in written for t in d.added]),
    ]
    configs = [(EXAMPLE_CONFIGS / f"Robot{i}.toml").read_bytes() for i in (1, 2)]
    config = tomllib.loads(configs[0].decode())
    del config["security"]
    config["discovery"] = {"method": "multicast", "cluster": "c1", "members": 3}
    config["central"] = "coap://127.0.0.1:5700"
    config["cost"] = {"reserve_wh": 10.0}
    import tomli_w

    out["config_toml"] = configs + [tomli_w.dumps(config).encode()]
    links = registration_links(_discovery_config()).encode()
    lookup = (b'<coap://127.0.0.1:5721>;ep="Robot1";d="c1";base="coap://127.0.0.1:5721",'
              b'<coap://127.0.0.1:5722>;ep="Robot2";base="coap://127.0.0.1:5722"')
    res_lookup = b'<coap://127.0.0.1:5721/kb>;rt="coapkb.kb";kb="Object";anchor="coap://127.0.0.1:5721"'
    answer = aiocoap.Message(code=Code.CONTENT, payload=b'<coap://127.0.0.1:5690/rd>;rt="core.rd"', content_format=40)
    answer.mtype, answer.mid, answer.token = aiocoap.NON, 9, ASKER_TOKEN
    ask = aiocoap.Message(code=Code.GET, uri_path=(".well-known", "core"), uri_query=("rt=core.rd*",))
    ask.mtype, ask.mid, ask.token = aiocoap.NON, 10, b"\x09"
    out["discovery_links"] = [
        b"\x00" + lookup, b"\x01" + res_lookup, b"\x02" + links, b"\x03" + answer.encode(), b"\x04" + ask.encode(),
    ]
    return out


def names() -> list[str]:
    return sorted(TARGETS)

