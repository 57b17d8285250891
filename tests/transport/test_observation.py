"""The observation registry that ZeroMQ, Zenoh and DDS share, in-process
against a recording notifier.  What observing does through each real
transport is the transport contract's (tests/transport/test_contract.py).

Every test that waits for something waits on the thing itself (an answer, a
notification, an event set by the service), never on a sleep.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import AsyncIterator, Callable, Coroutine, Hashable
from typing import Any

import pytest

from coapkb.transport.base import ResourceInfo, Service
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status
from coapkb.transport.observation import ObservationRegistry, ObserverState, put_latest

log = logging.getLogger(__name__)
COUNTER = Request(Method.GET, "/counter")


class CounterService(Service):
    """``/counter``: its value, or 4.04 once ``broken``.  While ``gate`` is
    clear, answers wait in :meth:`handle`, which sets ``entered``."""

    def __init__(self) -> None:
        self.value = 0
        self.broken = False
        self.gate = asyncio.Event()
        self.gate.set()
        self.entered = asyncio.Event()
        self.subscribers: list[Callable[[], None]] = []
        self.unsubscribed = asyncio.Event()
        self.refuse_subscriptions = False

    def resources(self) -> list[ResourceInfo]:
        return [ResourceInfo("/counter", obs=True)]

    async def handle(self, request: Request) -> Response:
        self.entered.set()
        await self.gate.wait()
        if self.broken:
            return Response.error(Status.NOT_FOUND, "gone")
        return Response(Status.CONTENT, str(self.value).encode(), ContentFormat.TEXT)

    def subscribe(self, path: str, on_change: Callable[[], None]) -> Callable[[], None]:
        if self.refuse_subscriptions:
            raise RuntimeError("a buggy service")
        self.subscribers.append(on_change)

        def cancel() -> None:
            self.subscribers.remove(on_change)
            self.unsubscribed.set()

        return cancel

    def bump(self) -> None:
        self.value += 1
        for on_change in list(self.subscribers):
            on_change()


class Recorder:
    """A transport's side of observations: records answers and notifications."""

    def __init__(self) -> None:
        self.answers: list[tuple[bytes, Status, int | None]] = []
        self.sent: asyncio.Queue[tuple[Hashable, bytes, Status, int]] = asyncio.Queue()
        self.closed: list[Hashable] = []
        self.reachable = True
        self.answer_gets_out = True
        self.gone: dict[Hashable, Callable[[], None]] = {}

    async def answer(self, response: Response, seq: int | None) -> bool:
        self.answers.append((response.payload, response.status, seq))
        return self.answer_gets_out

    def opener(self, key: Hashable) -> Callable[[Callable[[], None]], RecordingNotifier]:
        def open_notifier(gone: Callable[[], None]) -> RecordingNotifier:
            self.gone[key] = gone
            return RecordingNotifier(self, key)

        return open_notifier


class RecordingNotifier:
    def __init__(self, recorder: Recorder, key: Hashable) -> None:
        self.recorder = recorder
        self.key = key

    async def notify(self, response: Response, seq: int) -> bool:
        if not self.recorder.reachable:
            return False
        self.recorder.sent.put_nowait((self.key, response.payload, response.status, seq))
        return True

    def close(self) -> None:
        self.recorder.closed.append(self.key)


class Fixture:
    def __init__(self, *, limit: int = 4) -> None:
        self.service = CounterService()
        self.recorder = Recorder()
        self.tasks: set[asyncio.Task[None]] = set()
        self.registry = ObservationRegistry(
            self.service, slots=asyncio.Semaphore(4), spawn=self.spawn, limit=limit, log=log
        )

    def spawn(self, coro: Coroutine[Any, Any, None]) -> asyncio.Task[None]:
        task = asyncio.create_task(coro)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)
        return task

    async def register(self, client: Hashable = "a", key: Hashable = 1) -> None:
        await self.registry.register(client, key, COUNTER, self.recorder.answer, self.recorder.opener((client, key)))

    async def next_sent(self) -> tuple[Hashable, bytes, Status, int]:
        return await asyncio.wait_for(self.recorder.sent.get(), 5)

    async def aclose(self) -> None:
        self.registry.stop_all()
        await asyncio.gather(*self.tasks, return_exceptions=True)


@pytest.fixture
async def fx() -> AsyncIterator[Fixture]:
    fixture = Fixture()
    yield fixture
    await fixture.aclose()


# =========================================================================== the registry


async def test_registration_answers_seq_0_then_each_change_in_seq_order(fx: Fixture) -> None:
    await fx.register()
    assert fx.recorder.answers == [(b"0", Status.CONTENT, 0)]
    assert len(fx.registry) == 1 and len(fx.service.subscribers) == 1
    for expected in (1, 2, 3):
        fx.service.bump()
        assert await fx.next_sent() == (("a", 1), str(expected).encode(), Status.CONTENT, expected)
    workers = set(fx.tasks)
    fx.registry.deregister("a", 1)
    assert len(fx.registry) == 0 and fx.service.subscribers == []
    assert fx.recorder.closed == [("a", 1)]
    await asyncio.gather(*workers, return_exceptions=True)
    assert fx.tasks == set()  # the update task ends with its observation


async def test_changes_during_an_update_are_coalesced_into_the_latest_state(fx: Fixture) -> None:
    await fx.register()
    fx.service.gate.clear()
    fx.service.entered.clear()
    fx.service.bump()
    await fx.service.entered.wait()  # the update is being computed, held at the gate
    fx.service.bump()
    fx.service.bump()
    fx.service.gate.set()
    first, second = await fx.next_sent(), await fx.next_sent()
    assert [(first[1], first[3]), (second[1], second[3])] == [(b"3", 1), (b"3", 2)]
    assert fx.recorder.sent.empty()


async def test_a_change_during_the_first_answer_is_not_lost(fx: Fixture) -> None:
    fx.service.gate.clear()
    registering = asyncio.create_task(fx.register())
    await fx.service.entered.wait()  # subscribed, computing the first answer
    fx.service.bump()
    fx.service.gate.set()
    await registering
    assert fx.recorder.answers == [(b"1", Status.CONTENT, 0)]
    assert (await fx.next_sent())[1:] == (b"1", Status.CONTENT, 1)


async def test_an_error_at_registration_is_answered_without_seq_and_not_kept(fx: Fixture) -> None:
    fx.service.broken = True
    await fx.register()
    assert fx.recorder.answers == [(b"gone", Status.NOT_FOUND, None)]
    assert len(fx.registry) == 0 and fx.service.subscribers == [] and fx.recorder.closed == [("a", 1)]


async def test_an_error_notification_is_sent_and_ends_the_observation(fx: Fixture) -> None:
    await fx.register()
    fx.service.broken = True
    fx.service.bump()
    assert (await fx.next_sent())[2:] == (Status.NOT_FOUND, 1)
    await asyncio.gather(*fx.tasks)
    assert len(fx.registry) == 0 and fx.service.subscribers == []


async def test_an_observer_the_notifier_finds_gone_is_forgotten(fx: Fixture) -> None:
    await fx.register()
    fx.recorder.reachable = False
    fx.service.bump()
    await asyncio.wait_for(fx.service.unsubscribed.wait(), 5)
    assert len(fx.registry) == 0 and fx.recorder.closed == [("a", 1)]


async def test_a_transport_that_learns_of_a_vanished_observer_ends_it(fx: Fixture) -> None:
    await fx.register("a", 1)
    await fx.register("a", 2)
    fx.recorder.gone[("a", 1)]()
    assert len(fx.registry) == 1 and fx.recorder.closed == [("a", 1)]
    fx.recorder.gone[("a", 1)]()  # told twice: nothing more happens
    assert fx.recorder.closed == [("a", 1)]


async def test_deregistered_while_the_first_answer_is_computed_gets_no_answer(fx: Fixture) -> None:
    fx.service.gate.clear()
    registering = asyncio.create_task(fx.register())
    await fx.service.entered.wait()  # subscribed, computing the first answer
    fx.registry.deregister("a", 1)
    fx.service.gate.set()
    await registering
    assert fx.recorder.answers == [] and len(fx.registry) == 0 and fx.tasks == set()


async def test_a_first_answer_that_does_not_get_out_ends_the_observation(fx: Fixture) -> None:
    fx.recorder.answer_gets_out = False
    await fx.register()
    assert fx.recorder.answers == [(b"0", Status.CONTENT, 0)]
    assert len(fx.registry) == 0 and fx.service.subscribers == [] and fx.tasks == set()


async def test_the_limit_is_per_client_and_a_replaced_key_does_not_count() -> None:
    fx = Fixture(limit=2)
    try:
        await fx.register("a", 1)
        await fx.register("a", 1)  # the same key again: replaces the first
        assert len(fx.registry) == 1 and fx.recorder.closed == [("a", 1)]
        await fx.register("a", 2)
        await fx.register("a", 3)  # no slot left: answered, without seq
        await fx.register("b", 1)  # another client has its own slots
        assert [seq for _, _, seq in fx.recorder.answers] == [0, 0, 0, None, 0]
        assert len(fx.registry) == 3 and len(fx.service.subscribers) == 3
        fx.registry.forget_client("a")
        assert len(fx.registry) == 1 and len(fx.service.subscribers) == 1
        fx.service.bump()
        assert (await fx.next_sent())[0] == ("b", 1)
    finally:
        await fx.aclose()


async def test_no_notifier_or_a_failing_subscription_answers_without_seq(
    fx: Fixture, caplog: pytest.LogCaptureFixture
) -> None:
    await fx.registry.register("a", 1, COUNTER, fx.recorder.answer, lambda gone: None)
    assert fx.service.subscribers == []
    fx.service.refuse_subscriptions = True
    with caplog.at_level(logging.ERROR, logger=__name__):
        await fx.register("a", 2)
    assert "Service.subscribe('/counter') raised" in caplog.text
    assert [seq for _, _, seq in fx.recorder.answers] == [None, None]
    assert len(fx.registry) == 0 and fx.recorder.closed == [("a", 2)]


async def test_a_change_reported_from_another_thread_is_sent(fx: Fixture) -> None:
    await fx.register()
    thread = threading.Thread(target=fx.service.bump)
    thread.start()
    thread.join()
    assert (await fx.next_sent())[1:] == (b"1", Status.CONTENT, 1)


async def test_stop_all_ends_every_observation_and_its_update_task(fx: Fixture) -> None:
    await fx.register("a", 1)
    await fx.register("b", 1)
    workers = set(fx.tasks)
    assert len(workers) == 2
    fx.registry.stop_all()
    results = await asyncio.gather(*workers, return_exceptions=True)
    assert all(isinstance(r, asyncio.CancelledError) for r in results)
    assert len(fx.registry) == 0 and fx.service.subscribers == [] and len(fx.recorder.closed) == 2


# =========================================================================== the observing side


def test_observer_state_delivers_only_news_and_ends_on_an_error() -> None:
    ok = Response(Status.CONTENT, b"x")
    state = ObserverState(ok, 0)
    assert state.registered
    assert [state.accept(ok, seq) for seq in (2, 1, 2, None, 3)] == [True, False, False, False, True]
    assert state.accept(Response.error(Status.NOT_FOUND, "gone"), 4) and not state.registered
    assert not ObserverState(ok, None).registered  # answered, not registered (no slot)
    assert not ObserverState(Response.error(Status.NOT_FOUND, "gone"), 0).registered


def test_put_latest_drops_the_oldest() -> None:
    queue: asyncio.Queue[int] = asyncio.Queue(maxsize=2)
    for item in range(4):
        put_latest(queue, item)
    assert [queue.get_nowait(), queue.get_nowait()] == [2, 3]
