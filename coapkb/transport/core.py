"""The server and client core of the transports without CoAP's machinery.

ZeroMQ, Zenoh and DDS carry coapkb's requests in messages of their own
(docs/protocol.md); what each keeps is how those messages get in and out.
What they share lives here, once:

* :class:`CoreOptions`, the limits every one of them takes, under one name
  each; a transport's options class adds its own fields;
* :class:`ServerCore`: the counters, the handler tasks and their slots,
  malformed-message counting, the admission check before the service, the
  observation registry and the order of shutting down;
* :class:`ClientCore`: the counters, malformed-answer counting, the closed
  state, and the error a request cut short by :meth:`aclose` raises.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable, Coroutine, Hashable, Iterator
from dataclasses import dataclass, replace
from typing import Any, Self

from ..cancelling import cancel_and_wait
from .base import Endpoint, RateLimitedLog, Service, TrafficCounters, TransportError, handle_safely
from .envelope import encode_response
from .messages import Method, Request, Response, Status
from .observation import Answer, Notifier, ObservationRegistry, put_latest

__all__ = ["OBSERVABLE_METHODS", "ClientCore", "CoreOptions", "ServerCore", "check_scheme", "post"]

#: Methods an observation may be registered with (RFC 7641 and 8132).
OBSERVABLE_METHODS = (Method.GET, Method.FETCH)


@dataclass(frozen=True)
class CoreOptions:
    """Limits every transport built on the core takes."""

    #: Server: requests handled at once; further ones wait their turn.
    max_concurrent_requests: int = 64
    #: Server: observations one client may hold (a transport that tells no
    #: clients apart registers all under one: then a limit for the server).
    max_observations: int = 256
    #: Client: undelivered notifications kept per observation (oldest dropped first).
    observe_queue: int = 64
    #: Client: time an observe iterator waits for the first answer.
    observe_timeout_s: float = 10.0
    #: At most one "malformed message" warning per this many seconds.
    malformed_log_interval_s: float = 10.0

    def __post_init__(self) -> None:
        # ValueError "FIELD: why", as a robot's [transport.SCHEME] table reports it.
        for name in ("max_concurrent_requests", "observe_queue", "observe_timeout_s"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name}: must be positive, got {getattr(self, name)}")
        for name in ("max_observations", "malformed_log_interval_s"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name}: must not be negative, got {getattr(self, name)}")


def check_scheme(endpoint: Endpoint, *schemes: str) -> None:
    """ValueError unless ``endpoint`` has one of ``schemes``."""
    if endpoint.scheme not in schemes:
        raise ValueError(f"{endpoint} is not a {' or '.join(f'{s}://' for s in schemes)} endpoint")


def post(loop: asyncio.AbstractEventLoop, callback: Callable[..., None], *args: Any) -> None:
    """Run ``callback(*args)`` on ``loop`` from a library's own thread; a loop
    already closed (the transport is shutting down) has nobody to tell."""
    with contextlib.suppress(RuntimeError):
        loop.call_soon_threadsafe(callback, *args)


class _Endpoint:
    """What both ends count, and their closed state."""

    counters: TrafficCounters

    def __init__(self, options: CoreOptions, log: logging.Logger, name: str) -> None:
        self.counters = TrafficCounters()
        #: Messages dropped (or answered with an error) because they could not be decoded.
        self.malformed = 0
        self._log = log
        #: Who logs: ``"zmq server"``, ``"dds client"``, ...
        self._name = name
        self._bad_log = RateLimitedLog(log, options.malformed_log_interval_s)
        self._closed = False

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        """Close.  Idempotent."""
        self._closed = True

    def _count_received(self, size: int) -> None:
        self.counters.messages_received += 1
        self.counters.bytes_received += size

    def _count_sent(self, size: int) -> None:
        self.counters.messages_sent += 1
        self.counters.bytes_sent += size


class ServerCore(_Endpoint):
    """What a server of a transport without CoAP's machinery shares.

    A subclass receives messages its own way, counts them with
    :meth:`_count_received` (and :meth:`_malformed` when they are not a
    request), takes a slot, and hands each request to :meth:`_answer` in a
    task started by :meth:`_spawn`.  It sends through its own ``reply``
    callbacks and releases what it holds in :meth:`_close_transport`.
    """

    endpoint: Endpoint

    def __init__(self, service: Service, endpoint: Endpoint, options: CoreOptions, log: logging.Logger,
                 name: str) -> None:
        super().__init__(options, log, name)
        self.endpoint = endpoint
        self._service = service
        self._slots = asyncio.Semaphore(options.max_concurrent_requests)
        self._tasks: set[asyncio.Task[None]] = set()
        self._observations = ObservationRegistry(
            service, slots=self._slots, spawn=self._spawn, limit=options.max_observations, log=log
        )

    @property
    def observation_count(self) -> int:
        """Observations currently registered (all clients)."""
        return len(self._observations)

    async def aclose(self) -> None:
        """Stop serving: end observations, cancel and await handlers, then
        release the transport's own resources.  Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._stop_receiving()
        self._observations.stop_all()
        await cancel_and_wait(self._tasks)
        await self._close_transport()

    def _stop_receiving(self) -> None:
        """Take no more requests (before the handlers are cancelled)."""

    async def _close_transport(self) -> None:
        """Release sockets, sessions or participants (after the handlers ended)."""

    # ------------------------------------------------------------------ receiving

    def _malformed(self, source: str, why: str) -> None:
        self.malformed += 1
        self._bad_log.warning("%s %s: dropped malformed message from %s: %s (%d dropped so far)",
                              self._name, self.endpoint, source, why[:200], self.malformed)

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> asyncio.Task[None]:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._task_done)
        return task

    def _task_done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            self._log.error("%s %s: handler crashed", self._name, self.endpoint, exc_info=task.exception())

    # ------------------------------------------------------------------ answering

    def _refusal(self, sender: str | None, method: Method, path: str) -> Response | None:
        """The service's answer to a request it does not admit, else None."""
        return self._service.admit(sender, str(method.value), path)

    async def _call(self, request: Request) -> Response:
        return await handle_safely(self._service, request, self._log)

    def _encoded(self, token: int, response: Response, seq: int | None = None) -> bytes:
        """``response`` in the CBOR envelope (ZeroMQ, DDS); one the envelope
        cannot carry is the service's bug, answered 5.00."""
        try:
            return encode_response(token, response, seq=seq)
        except ValueError as exc:
            self._log.error("%s %s: service returned an unencodable response: %s", self._name, self.endpoint, exc)
            return encode_response(token, Response.error(Status.INTERNAL_SERVER_ERROR, "internal error"), seq=seq)

    async def _answer(
        self,
        request: Request,
        reply: Answer,
        *,
        sender: str | None,
        observe: tuple[Hashable, Hashable] | None = None,
        notifier: Callable[[Callable[[], None]], Notifier | None] | None = None,
    ) -> None:
        """Admit ``request`` from ``sender`` and answer it through ``reply``.

        With ``observe`` (the observer's client and key) and ``notifier`` (the
        way to it) an observable request registers an observation.  A refused
        request never reaches the service, so it changes nothing."""
        refused = self._refusal(sender, request.method, request.path)
        if refused is not None:
            await reply(refused, None)
            return
        request = replace(request, peer=sender)
        if observe is not None and notifier is not None and request.method in OBSERVABLE_METHODS:
            client, key = observe
            await self._observations.register(client, key, request, reply, notifier)
        else:
            await reply(await self._call(request), None)


class ClientCore(_Endpoint):
    """What a client of a transport without CoAP's machinery shares; a
    subclass's :meth:`aclose` releases what it holds and calls
    :meth:`_end_observations`."""

    def __init__(self, options: CoreOptions, log: logging.Logger, name: str) -> None:
        super().__init__(options, log, name)
        #: The notification queues of the observations running on this client.
        self._observing: set[asyncio.Queue[Any]] = set()

    @contextlib.contextmanager
    def _observation(self, queue: asyncio.Queue[Any]) -> Iterator[asyncio.Queue[Any]]:
        """``queue`` gets a :class:`TransportError` if the client closes
        while the observation runs (its reader raises it: never a wait for ever)."""
        self._observing.add(queue)
        try:
            yield queue
        finally:
            self._observing.discard(queue)

    def _end_observations(self) -> None:
        closed = TransportError(f"the {self._name} transport was closed")
        for queue in self._observing:
            put_latest(queue, closed)

    def _malformed(self, peer: Endpoint, why: str) -> None:
        self.malformed += 1
        self._bad_log.warning("%s: dropped malformed answer from %s: %s", self._name, peer, why[:200])

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError(f"the {self._name} transport is closed")

    def _closed_error(self) -> TransportError | None:
        """If :meth:`aclose` cut a request short, the error that says so, instead
        of a CancelledError nobody asked for (None: a real cancellation)."""
        task = asyncio.current_task()
        if self._closed and (task is None or not task.cancelling()):
            return TransportError(f"the {self._name} transport was closed")
        return None
