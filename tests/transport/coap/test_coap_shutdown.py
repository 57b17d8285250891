"""A CoAP server closed while aiocoap still owes a CON request its empty
ACK: aiocoap's shutdown leaves that timer running, and one that fired after
the socket closed raised inside an asyncio callback (a traceback in a
robot's log at SIGTERM)."""

from __future__ import annotations

import asyncio
import socket
from typing import Any

from aiocoap.numbers.constants import TransportTuning

from coapkb.transport import Endpoint, ResourceInfo, serve
from coapkb.transport.messages import Request, Response
from coapkb.transport.router import Router


async def test_closing_with_an_empty_ack_pending_raises_nothing_later() -> None:
    loop = asyncio.get_running_loop()
    errors: list[dict[str, Any]] = []
    previous = loop.get_exception_handler()
    loop.set_exception_handler(lambda _loop, context: errors.append(context))
    arrived = asyncio.Event()

    async def never_answers(request: Request) -> Response:
        arrived.set()
        await asyncio.Event().wait()  # cancelled by the shutdown
        raise AssertionError("unreachable")

    router = Router()
    router.add(ResourceInfo("/slow"), never_answers)
    server = await serve(router, Endpoint("coap", "127.0.0.1", 0))
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        # CON GET /slow (RFC 7252 section 3): version 1, CON, a 2-byte token; MID 0x1234; Uri-Path "slow".
        request = bytes([0x42, 0x01, 0x12, 0x34, 0x01, 0x02, 0xB4]) + b"slow"
        sock.sendto(request, ("127.0.0.1", server.endpoint.port))
        async with asyncio.timeout(30):
            await arrived.wait()
        await server.aclose()  # the empty ACK is still owed (EMPTY_ACK_DELAY after arrival)
        # Nothing to await: the timer must simply never fire.  Wait it out, with room.
        await asyncio.sleep(TransportTuning.EMPTY_ACK_DELAY * 5)
    finally:
        sock.close()
        loop.set_exception_handler(previous)
    assert errors == []
