"""The one module that touches aiocoap's private names: it must fail loudly,
in this test, when aiocoap changes under it."""

from __future__ import annotations

import aiocoap
import aiocoap.meta
import pytest

from coapkb.transport.coap import aiocoap_adapter
from coapkb.transport.coap.aiocoap_adapter import ContextHooks, UnsupportedAiocoapVersion, verify


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


def test_the_pipe_logger_takes_aiocoaps_exception_keyword(caplog: pytest.LogCaptureFixture) -> None:
    import logging

    log = aiocoap_adapter._PipeSafeLogger(logging.getLogger("coapkb.test.pipe"))
    with caplog.at_level(logging.ERROR, logger="coapkb.test.pipe"):
        log.error("Discarded exception in %r", "event", exception=RuntimeError("late"))
    assert "late" in caplog.text
