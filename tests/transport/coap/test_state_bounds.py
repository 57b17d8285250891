"""The state a stranger's datagrams can make a CoAP server keep stays within
its written bounds (docs/flood.md): the bounded map itself, block-wise
transfers in and out, and aiocoap's duplicate memory, on real messages."""

from __future__ import annotations

import asyncio
import socket
import struct

import aiocoap
import pytest
from aiocoap.optiontypes import BlockOption

from coapkb.transport.coap import aiocoap_adapter
from coapkb.transport.coap.aiocoap_adapter import ContextHooks, ContinueException, IncompleteException
from coapkb.transport.coap.blockwise import BodyAwareBlock2Cache, GapSafeBlock1Spool
from coapkb.transport.coap.bounds import MESSAGE_OVERHEAD, StateBounds
from coapkb.transport.expiring import ExpiringMap


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_the_map_keeps_its_three_bounds_least_recently_used_out_first() -> None:
    clock = Clock()
    m: ExpiringMap[str, bytes] = ExpiringMap(ttl_s=10, max_entries=3, max_bytes=100, size=len, clock=clock)
    m["a"], m["b"], m["c"] = b"x" * 10, b"x" * 10, b"x" * 10
    assert m["a"] == b"x" * 10  # a used: b is now the oldest
    m["d"] = b"x" * 10  # a fourth entry: b goes
    assert list(m) == ["c", "a", "d"]
    m["e"] = b"x" * 90  # 120 bytes: the oldest go until 100 fit
    assert list(m) == ["d", "e"] and m.bytes == 100
    m["f"] = b"x" * 101  # larger than the whole map: not kept
    assert "f" not in m and list(m) == ["d", "e"]
    clock.now = 10.0  # unused for ttl_s: gone at the next touch
    assert "e" not in m and len(m) == 0 and m.bytes == 0


def test_replacing_an_entry_counts_its_new_size() -> None:
    m: ExpiringMap[str, bytes] = ExpiringMap(ttl_s=10, max_entries=3, max_bytes=100, size=len, clock=Clock())
    m["a"] = b"x" * 60
    m["a"] = b"x" * 20
    m["b"] = b"x" * 70
    assert m.bytes == 90 and list(m) == ["a", "b"]
    assert m.pop("a") == b"x" * 20 and m.bytes == 70


@pytest.mark.parametrize("bounds", [dict(ttl_s=0, max_entries=1, max_bytes=1), dict(ttl_s=1, max_entries=0, max_bytes=1)])
def test_bounds_must_be_positive(bounds: dict) -> None:
    with pytest.raises(ValueError, match="bounds must be positive"):
        ExpiringMap(size=len, **bounds)


async def _server_context() -> tuple[aiocoap.Context, int]:
    ctx = await aiocoap.Context.create_server_context(aiocoap.resource.Site(), bind=("127.0.0.1", 0),
                                                      transports=["udp6"])
    return ctx, aiocoap_adapter.local_port(ctx)


async def _received(ctx: aiocoap.Context, port: int, datagram: bytes) -> aiocoap.Message:
    """``datagram`` sent to ``ctx`` over a real socket, as aiocoap decoded it."""
    seen: asyncio.Future[aiocoap.Message] = asyncio.get_running_loop().create_future()
    hooks = ContextHooks.of(ctx)
    original = hooks.mm.dispatch_message

    def catch(message: aiocoap.Message) -> None:
        if not seen.done():
            seen.set_result(message)

    hooks.mm.dispatch_message = catch
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.sendto(datagram, ("127.0.0.1", port))
            return await asyncio.wait_for(seen, 5)
    finally:
        hooks.mm.dispatch_message = original


def _fetch(mid: int, payload: bytes, block1: tuple[int, bool, int] | None = None) -> bytes:
    """CON FETCH /kb/sparql (text/plain), token 0xB1, with a Block1 option (number, more, szx)."""
    msg = aiocoap.Message(code=aiocoap.FETCH, uri_path=("kb", "sparql"), content_format=0, payload=payload)
    msg.mtype, msg.mid, msg.token = aiocoap.CON, mid, b"\xb1"  # as on the wire, not as a client would
    if block1 is not None:
        msg.opt.block1 = BlockOption.BlockwiseTuple(*block1)
    return msg.encode()


async def test_block1_assemblies_are_bounded_in_number_and_a_dropped_one_is_4_08() -> None:
    spool = GapSafeBlock1Spool(StateBounds(block1_assemblies=4))
    ctx, port = await _server_context()
    try:
        first_blocks = []
        for mid in range(6):  # six requests start, from six source ports: six keys
            first_blocks.append(await _received(ctx, port, _fetch(mid, b"#" * 64, block1=(0, True, 2))))
        for req in first_blocks:
            with pytest.raises(ContinueException):
                spool.feed_and_take(req)
        assert len(spool._assemblies) == 4
        # the oldest two were dropped: their next block is Incomplete, the newest's completes
        last = [await _received(ctx, port, _fetch(10 + mid, b"?", block1=(1, False, 2))) for mid in range(2)]
        for req, first in zip(last, first_blocks):
            req.remote = first.remote
            with pytest.raises(IncompleteException):
                spool.feed_and_take(req)
        done = await _received(ctx, port, _fetch(20, b"ASK {}", block1=(1, False, 2)))
        done.remote = first_blocks[-1].remote
        assert spool.feed_and_take(done).payload == b"#" * 64 + b"ASK {}"
    finally:
        await ctx.shutdown()


async def test_block2_answers_are_bounded_in_bytes() -> None:
    cache = BodyAwareBlock2Cache(bounds=StateBounds(block2_bytes=3 * (2048 + MESSAGE_OVERHEAD)))
    ctx, port = await _server_context()
    try:
        for mid in range(5):  # five different 2 kB answers, each from its own source port
            req = await _received(ctx, port, _fetch(mid, b"query %d" % mid))

            async def answer(n: int = mid) -> aiocoap.Message:
                return aiocoap.Message(code=aiocoap.CONTENT, payload=bytes([n]) * 2048)

            first = await cache.extract_or_insert(req, answer)
            assert first.opt.block2.more
        assert len(cache._transfers) == 3
        assert cache._transfers.bytes <= cache._transfers.max_bytes
    finally:
        await ctx.shutdown()


async def test_the_duplicate_memory_keeps_at_most_its_answer_bytes() -> None:
    ctx, port = await _server_context()
    hooks = ContextHooks.of(ctx, StateBounds(duplicate_answer_bytes=4096))
    try:
        recent = hooks.mm._recent_messages
        for mid in range(8):
            req = await _received(ctx, port, _fetch(mid, b"q"))
            assert hooks._deduplicate_message(req) is False
            recent[(req.remote, req.mid)] = aiocoap.Message(code=aiocoap.CONTENT, payload=b"x" * 1024)
        hooks.forget_duplicates()
        assert recent.answer_bytes <= 4096 and len(recent) == 4096 // (1024 + MESSAGE_OVERHEAD)
        assert len(recent.came) == len(recent)
    finally:
        hooks.remove()
        await ctx.shutdown()


async def test_a_resource_keeps_at_most_its_bound_of_observations() -> None:
    """Past ``observers``, a registration gets the state without Observe (RFC 7641 section 4.1)."""
    from coapkb.transport import Endpoint
    from coapkb.transport.base import ResourceInfo
    from coapkb.transport.coap import CoapServerTransport
    from coapkb.transport.messages import Response, Status
    from coapkb.transport.router import Router

    router = Router()

    async def state(request) -> Response:  # type: ignore[no-untyped-def]
        return Response(Status.CONTENT, b"idle")

    router.add(ResourceInfo("/state", obs=True), state)
    server = await CoapServerTransport.start(router, Endpoint("coap", "127.0.0.1", 0), bounds=StateBounds(observers=3))
    observed = []
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.settimeout(5)
            for n in range(5):
                msg = aiocoap.Message(code=aiocoap.GET, uri_path=("state",), observe=0)
                msg.mtype, msg.mid, msg.token = aiocoap.CON, 100 + n, bytes([n + 1])
                sock.sendto(msg.encode(), ("127.0.0.1", server.endpoint.port))
                answer = aiocoap.Message.decode(await asyncio.to_thread(sock.recv, 2048))
                assert answer.payload == b"idle"
                observed.append(answer.opt.observe is not None)
    finally:
        await server.aclose()
    assert observed == [True, True, True, False, False]


async def test_an_idle_server_forgets_aged_block_transfers_and_trims_its_heap(monkeypatch) -> None:
    """The server's sweep, not a new request, ages state out."""
    from coapkb.transport import Endpoint, open_client
    from coapkb.transport.base import ResourceInfo
    from coapkb.transport.coap import CoapServerTransport, heap
    from coapkb.transport.coap import server as coap_server
    from coapkb.transport.messages import Method, Request, Response, Status
    from coapkb.transport.router import Router

    trims = []
    monkeypatch.setattr(coap_server, "trim_heap", lambda: trims.append(heap.trim_heap()))
    router = Router()

    async def big(request) -> Response:  # type: ignore[no-untyped-def]
        return Response(Status.CONTENT, bytes(range(256)) * 12)

    router.add(ResourceInfo("/big"), big)
    bounds = StateBounds(transfer_idle_s=0.3, sweep_every_s=0.1, trim_after_bytes=1)
    server = await CoapServerTransport.start(router, Endpoint("coap", "127.0.0.1", 0), bounds=bounds)
    client = await open_client("coap")
    try:
        answer = await client.request(server.endpoint, Request(Method.GET, "/big"), timeout=5)
        assert len(answer.payload) == 3072
        transfers = server.blocks[1]._transfers
        assert len(transfers._items) == 1
        for _ in range(100):  # the sweep runs every 0.1 s; give it up to 10 s on a loaded machine
            if not transfers._items and trims:
                break
            await asyncio.sleep(0.1)
        assert not transfers._items and trims[0] is True
    finally:
        await client.aclose()
        await server.aclose()


async def test_unknown_option_numbers_and_content_formats_leave_nothing_behind() -> None:
    """aiocoap kept a member of its enums for every unknown option number or
    content format a datagram named, for good; a stranger's garbage grew the process."""
    from aiocoap.numbers.contentformat import ContentFormat
    from aiocoap.numbers.optionnumbers import OptionNumber

    ctx, port = await _server_context()
    try:
        known = len(OptionNumber._value2member_map_), len(ContentFormat._value2member_map_)
        for n in range(200):
            # a NON GET with one elective option of a number nobody registered
            # (2000 + 2n: even = elective), and an Accept (17) of a format nobody registered
            delta = 2000 + 2 * n - 269
            datagram = (bytes([0x50, 0x01]) + struct.pack("!H", n) + bytes([0xD2, 17 - 13]) + struct.pack("!H", 30000 + n)
                        + bytes([0xE1]) + struct.pack("!H", delta - 17) + b"x")
            message = await _received(ctx, port, datagram)
            assert message.opt.accept == 30000 + n
        assert (len(OptionNumber._value2member_map_), len(ContentFormat._value2member_map_)) == known
        assert OptionNumber(2000) == 2000 and OptionNumber(11) is OptionNumber.URI_PATH
    finally:
        await ctx.shutdown()


def test_a_bound_that_keeps_nothing_is_refused() -> None:
    with pytest.raises(ValueError, match="StateBounds.observers must be positive"):
        StateBounds(observers=0)
    assert StateBounds(duplicate_horizon_s=0.0).duplicate_horizon_s == 0.0  # remember only until the next request
