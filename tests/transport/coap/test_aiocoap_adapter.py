"""The one module that touches aiocoap's private names: it must fail loudly,
in this test, when aiocoap changes under it."""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Iterator

import aiocoap
import aiocoap.meta
import aiocoap.resource
import pytest

from coapkb.transport.coap import aiocoap_adapter
from coapkb.transport.coap.aiocoap_adapter import ContextHooks, UnsupportedAiocoapVersion, verify
from coapkb.transport.coap.bounds import StateBounds


def test_every_private_name_is_where_the_adapter_expects_it() -> None:
    verify()  # the pinned version, every hooked method's parameters, the block helpers


def test_another_aiocoap_version_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(aiocoap.meta, "version", "0.4.18")
    with pytest.raises(UnsupportedAiocoapVersion, match="0.4.17"):
        verify()


def test_a_changed_signature_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    from aiocoap.messagemanager import MessageManager

    def _retransmit(self, message, timeout):  # one parameter fewer
        raise AssertionError("never called")

    monkeypatch.setattr(MessageManager, "_retransmit", _retransmit)
    with pytest.raises(UnsupportedAiocoapVersion, match="_retransmit"):
        verify()


async def test_hooks_are_per_context_and_come_off_whole() -> None:
    a = await aiocoap.Context.create_client_context(transports=["udp6"])
    b = await aiocoap.Context.create_client_context(transports=["udp6"])
    try:
        hooks = ContextHooks.of(a)
        assert ContextHooks.of(a) is hooks
        mm_a = a.request_interfaces[0].token_interface
        mm_b = b.request_interfaces[0].token_interface
        assert "send_message" in vars(mm_a) and "send_message" not in vars(mm_b)
        original_log = a.log
        assert isinstance(vars(a)["log"], aiocoap_adapter._PipeSafeLogger)
    finally:
        await a.shutdown()
        await b.shutdown()
    hooks.remove()
    assert "send_message" not in vars(mm_a) and vars(a)["log"] is original_log.logger


async def test_an_icmp_error_read_after_a_broken_off_shutdown_reaches_nobody() -> None:
    """aiocoap's context shutdown can stop between its token layer and its
    socket (an observation's error); an ICMP error read then met a token
    manager already gone and raised (a traceback at a team's Ctrl-C)."""
    from aiocoap import GET, Message

    ctx = await aiocoap.Context.create_client_context(transports=["udp6"])
    hooks = ContextHooks.of(ctx)
    remote = await hooks.interface.determine_remote(Message(code=GET, uri="coap://127.0.0.1:9/x"))
    hooks.mm.token_manager.incoming_requests = None  # where the broken-off shutdown left it
    hooks.remove()
    hooks.mm.dispatch_error(ConnectionRefusedError(111, "Connection refused"), remote)  # no AttributeError
    await hooks.close_socket()
    assert hooks.mm._active_exchanges is None and hooks.interface.transport._protocol is None  # closed


def test_the_pipe_logger_takes_aiocoaps_exception_keyword(caplog: pytest.LogCaptureFixture) -> None:
    import logging

    log = aiocoap_adapter._PipeSafeLogger(logging.getLogger("coapkb.test.pipe"))
    with caplog.at_level(logging.ERROR, logger="coapkb.test.pipe"):
        log.error("Discarded exception in %r", "event", exception=RuntimeError("late"))
        # An abandoned OSCORE request meeting its cancelled answer: nobody waits for it.
        log.error("Discarded exception in %r", "abandoned", exception=asyncio.InvalidStateError("invalid state"))
    assert "late" in caplog.text and "abandoned" not in caplog.text


async def test_a_dead_peers_icmp_error_does_not_fail_the_next_send_to_a_live_one() -> None:
    """Linux reports one peer's ICMP "port unreachable" from the socket's next
    sendmsg, whoever it goes to; unhooked aiocoap blamed the live peer and
    dropped its datagram (a dead robot made a live teammate look dead)."""
    from aiocoap import GET, NON, Message

    from tests.support import free_udp_port

    live = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    live.bind(("127.0.0.1", 0))
    live.setblocking(False)
    dead_port = free_udp_port()
    ctx = await aiocoap.Context.create_client_context(transports=["udp6"])
    try:
        hooks = ContextHooks.of(ctx)
        remotes = []
        for port in (dead_port, live.getsockname()[1]):
            probe = Message(code=GET, uri=f"coap://127.0.0.1:{port}/x")
            remotes.append(await hooks.interface.determine_remote(probe))
        errors: list[tuple[Exception, object]] = []
        reported = asyncio.get_running_loop().create_future()
        original = hooks.mm.dispatch_error

        def record(error: Exception, remote: object) -> None:
            errors.append((error, remote))
            if not reported.done():
                reported.set_result(None)
            original(error, remote)

        hooks.mm.dispatch_error = record
        for mid, remote in enumerate(remotes * 2):  # dead, live, dead, live; the loop never runs in between
            message = Message(code=GET, uri_path=("x",))
            message.mtype, message.mid, message.token, message.remote = NON, mid + 1, b"t", remote
            hooks.interface.send(message)
        await asyncio.wait_for(reported, 2)  # the loop read the error queue
        assert len(live.recv(64)) > 0 and len(live.recv(64)) > 0  # both datagrams reached the live peer
        assert errors and all(remote == remotes[0] for _, remote in errors), errors
        assert hooks.counters.messages_sent == 4
    finally:
        await ctx.shutdown()
        live.close()


async def test_a_cancelled_blockwise_result_is_not_logged_as_an_error(caplog: pytest.LogCaptureFixture) -> None:
    """aiocoap's block-wise runner may set the result of a request its caller
    already cancelled; the InvalidStateError it then logs is not an error."""
    import logging

    ctx = await aiocoap.Context.create_client_context(transports=["udp6"], loggername="coapkb.test.client")
    try:
        ContextHooks.of(ctx)
        log = ctx.log.getChild(aiocoap_adapter.BLOCKWISE_LOGGER)
        with caplog.at_level(logging.DEBUG, logger="coapkb.test.client"):
            log.error("Exception in BlockwiseRequest runner: %s", "invalid state",
                      exc_info=asyncio.InvalidStateError("invalid state"))
            log.error("something else went wrong", exc_info=RuntimeError("boom"))
        levels = {r.getMessage(): r.levelno for r in caplog.records}
        assert levels == {"Exception in BlockwiseRequest runner: invalid state": logging.DEBUG,
                          "something else went wrong": logging.ERROR}
    finally:
        await ctx.shutdown()


class _Counting(aiocoap.resource.Resource):
    def __init__(self) -> None:
        super().__init__()
        self.calls = 0

    async def render_get(self, request: aiocoap.Message) -> aiocoap.Message:
        self.calls += 1
        return aiocoap.Message(payload=str(self.calls).encode())


async def _counting_server(bounds: StateBounds = StateBounds()) -> tuple[aiocoap.Context, _Counting, int]:
    from tests.support import free_udp_port

    resource = _Counting()
    site = aiocoap.resource.Site()
    site.add_resource(["n"], resource)
    port = free_udp_port()
    ctx = await aiocoap.Context.create_server_context(site, bind=("127.0.0.1", port), transports=["udp6"])
    ContextHooks.of(ctx, bounds)
    return ctx, resource, port


async def _ask(sock: socket.socket, port: int, mid: int, token: bytes | None = None) -> bytes:
    """One CON GET /n with this Message ID (and token: by default the ID's
    bytes) from a plain socket; the answer's payload."""
    from aiocoap import CON, GET, Message

    request = Message(code=GET, uri_path=("n",))
    request.mtype, request.mid, request.token = CON, mid, mid.to_bytes(2, "big") if token is None else token
    loop = asyncio.get_running_loop()
    await loop.sock_sendto(sock, request.encode(), ("127.0.0.1", port))
    while True:
        answer = Message.decode(await asyncio.wait_for(loop.sock_recv(sock, 2048), 10))
        if answer.mid == mid:
            return answer.payload


@pytest.fixture
def client_socket() -> Iterator[socket.socket]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    yield sock
    sock.close()


async def test_the_duplicate_memory_is_bounded_in_size_and_answers_a_recent_duplicate_again(
    monkeypatch: pytest.MonkeyPatch, client_socket: socket.socket
) -> None:
    ctx, resource, port = await _counting_server(StateBounds(duplicates=32))
    try:
        mm = ContextHooks.of(ctx).mm
        timers = len(asyncio.get_running_loop()._scheduled)  # type: ignore[attr-defined]
        for mid in range(1, 201):
            assert await _ask(client_socket, port, mid) == str(mid).encode()
        assert len(mm._recent_messages) <= 32
        # No timer left behind per request (aiocoap's own keeps one for 247 s each).
        assert len(asyncio.get_running_loop()._scheduled) < timers + 32  # type: ignore[attr-defined]
        # A retransmission of the latest request is a duplicate: the same answer, not run again.
        assert await _ask(client_socket, port, 200) == b"200"
        assert resource.calls == 200
        # One evicted long ago is new again (every robot resource is idempotent or keyed by task).
        assert await _ask(client_socket, port, 1) == b"201"
    finally:
        await ctx.shutdown()


async def test_a_message_id_reused_with_another_token_is_a_new_request(client_socket: socket.socket) -> None:
    """A client started again on the same port (a restarted robot, each run
    of ``coap-client -p``) cannot know the Message IDs its predecessor used:
    the same ID with another token is a new exchange, answered afresh, not a
    retransmission answered with the old exchange's answer (a libcoap interop
    test once got a block of another answer)."""
    ctx, resource, port = await _counting_server()
    try:
        assert await _ask(client_socket, port, 9, b"old") == b"1"
        assert await _ask(client_socket, port, 9, b"old") == b"1"  # a retransmission: the same answer
        assert await _ask(client_socket, port, 9, b"new") == b"2"  # a new client's request
        assert await _ask(client_socket, port, 9, b"new") == b"2"  # ... whose retransmission is a duplicate
        assert resource.calls == 2
    finally:
        await ctx.shutdown()


async def test_the_duplicate_memory_forgets_a_request_older_than_its_horizon(
    monkeypatch: pytest.MonkeyPatch, client_socket: socket.socket
) -> None:
    # every entry is old at the next request
    ctx, resource, port = await _counting_server(StateBounds(duplicate_horizon_s=0.0))
    try:
        assert await _ask(client_socket, port, 7) == b"1"
        assert await _ask(client_socket, port, 7) == b"1"  # nothing newer came: still remembered
        assert await _ask(client_socket, port, 8) == b"2"  # ... which ages 7 out
        assert await _ask(client_socket, port, 7) == b"3"
        assert len(ContextHooks.of(ctx).mm._recent_messages) == 1
    finally:
        await ctx.shutdown()


async def test_an_error_for_an_observation_cancelled_before_its_answer_is_not_logged(
        caplog: pytest.LogCaptureFixture) -> None:
    """An observation its caller gave up before the first answer, whose
    request then fails (the robot died: ICMP port unreachable): aiocoap
    raises from the error dispatch and logged a traceback as an error
    (``coapkb team`` stopped with Ctrl-C while its robots went down)."""
    import logging

    from aiocoap import GET, Message

    from tests.support import free_udp_port

    ctx = await aiocoap.Context.create_client_context(transports=["udp6"], loggername="coapkb.test.client")
    try:
        ContextHooks.of(ctx)
        with caplog.at_level(logging.DEBUG):
            request = ctx.request(Message(code=GET, observe=0, uri=f"coap://127.0.0.1:{free_udp_port()}/x"),
                                  handle_blockwise=False)
            request.observation.cancel()
            with pytest.raises(aiocoap.error.NetworkError):
                await asyncio.wait_for(request.response, 5)
        assert [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING] == []
        assert any("cancelled observation" in r.getMessage() for r in caplog.records)
    finally:
        await ctx.shutdown()
