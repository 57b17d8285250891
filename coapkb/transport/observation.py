"""Observe for transports that have none of their own (ZeroMQ, Zenoh).

CoAP has Observe (RFC 7641) built in; ZeroMQ and Zenoh carry the same
semantics on top of their own messages, and this module is what they share.

Server side: :class:`ObservationRegistry`
    Holds who observes what.  Registering subscribes to the resource through
    :meth:`Service.subscribe` *before* the first answer is computed (a change
    during it is not lost), answers the current state with ``seq`` 0, and
    from then on re-runs the request after each change and hands the answer,
    with the next ``seq``, to the observation's :class:`Notifier` -- the one
    transport-specific part: how a notification reaches that observer.
    Changes that arrive while an update is being computed are coalesced (an
    observer gets the latest state, not every intermediate one); updates of
    one observation go out one at a time, in ``seq`` order.  An error answer
    ends the observation, as does a notifier that finds its observer gone.
    A client without a free slot (``limit``), or a resource whose
    subscription fails, is answered without ``seq``: not registered.

Client side: :class:`ObserverState` and :func:`put_latest`
    Which notifications are news (a higher ``seq`` than the last one
    delivered) and whether the server still holds the observation; the
    notification queue keeps the newest states when the reader is slow.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable, Coroutine, Hashable
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar

from .base import Service, TransportError, handle_safely
from .messages import Request, Response

__all__ = [
    "Answer",
    "Delivery",
    "Notifier",
    "ObservationRegistry",
    "ObserverState",
    "put_latest",
]

_T = TypeVar("_T")

#: A response and its ``seq`` (None: not part of an observation).
Delivery = tuple[Response, int | None]

#: Sends the answer to a registration on the transport: the response and its
#: ``seq`` (0: registered, None: not).  False if it did not get out (the
#: observation is then not started).
Answer = Callable[[Response, int | None], Awaitable[bool]]


class Notifier(Protocol):
    """How notifications reach one observer on one transport."""

    async def notify(self, response: Response, seq: int) -> bool:
        """Send one notification.  False: the observer is gone (the observation ends)."""
        ...

    def close(self) -> None:
        """Release what reaching the observer holds; called once, when the observation ends."""
        ...


@dataclass(eq=False)
class _Observation:
    """One registered observer: whose, under which key, of what."""

    client: Hashable
    key: Hashable
    request: Request
    notifier: Notifier | None = None
    dirty: asyncio.Event = field(default_factory=asyncio.Event)
    #: The ``seq`` of the last answer sent (0: the registration's).
    seq: int = 0
    active: bool = True
    unsubscribe: Callable[[], None] | None = None
    worker: asyncio.Task[None] | None = None
    #: Notify only a changed answer (the resource is ``quiet``); the last one sent.
    quiet: bool = False
    last: Response | None = None


class ObservationRegistry:
    """The observations one server holds, and the tasks that push their updates.

    ``slots`` is the server's concurrency limit: each update is computed
    holding one (a registration runs in its caller's slot).  Update tasks
    are started with ``spawn``, so the server cancels and awaits them with
    its other handlers.  ``limit`` is the number of observations one client
    may hold; a transport that tells no clients apart registers all under
    one client, which makes it a limit for the server.  Log records go to
    the transport's ``log``.
    """

    def __init__(
        self,
        service: Service,
        *,
        slots: asyncio.Semaphore,
        spawn: Callable[[Coroutine[Any, Any, None]], asyncio.Task[None]],
        limit: int,
        log: logging.Logger,
    ) -> None:
        self._service = service
        self._slots = slots
        self._spawn = spawn
        self._limit = limit
        self._log = log
        self._by_client: dict[Hashable, dict[Hashable, _Observation]] = {}

    def __len__(self) -> int:
        """Observations currently registered (all clients)."""
        return sum(len(per) for per in self._by_client.values())

    async def _call(self, request: Request) -> Response:
        return await handle_safely(self._service, request, self._log)

    async def register(
        self,
        client: Hashable,
        key: Hashable,
        request: Request,
        answer: Answer,
        open_notifier: Callable[[Callable[[], None]], Notifier | None],
    ) -> None:
        """Register ``client``'s observation ``key`` of ``request`` and answer it.

        An observation under the same client and key is replaced.
        ``open_notifier(gone)`` sets up the transport's way to the observer
        (None if it cannot: the request is answered without ``seq``);
        ``gone()`` ends this observation, for a transport that learns
        about a vanished observer by itself.
        """
        if (old := self._by_client.get(client, {}).get(key)) is not None:
            self._stop(old)
        if len(self._by_client.get(client, {})) >= self._limit:
            # Like a CoAP server out of observer slots: answer, but without seq.
            await answer(await self._call(request), None)
            return
        quiet = any(info.quiet for info in self._service.resources() if info.path == request.path)
        obs = _Observation(client, key, request, quiet=quiet)
        obs.notifier = open_notifier(lambda: self._stop(obs))
        if obs.notifier is None:
            await answer(await self._call(request), None)
            return
        loop = asyncio.get_running_loop()

        def on_change() -> None:
            # call_soon_threadsafe: the service may change state from a thread;
            # a loop that is gone has nobody to tell.
            if obs.active:
                with contextlib.suppress(RuntimeError):
                    loop.call_soon_threadsafe(obs.dirty.set)

        try:
            obs.unsubscribe = self._service.subscribe(request.path, on_change)
        except Exception:  # noqa: BLE001 - a service's hook is its own code: the server goes on
            self._log.exception("Service.subscribe(%r) raised; answering without observation", request.path)
            self._stop(obs)
            await answer(await self._call(request), None)
            return
        # Subscribed before the first GET, so a change during it is not lost.
        self._by_client.setdefault(client, {})[key] = obs
        response = await self._call(request)
        if not obs.active:  # deregistered (or the client left) meanwhile
            return
        if not response.status.is_success:
            self._stop(obs)
            await answer(response, None)
            return
        obs.last = response
        if await answer(response, 0) and obs.active:
            obs.worker = self._spawn(self._notify_loop(obs))
        else:
            self._stop(obs)

    async def _notify_loop(self, obs: _Observation) -> None:
        """Send the current state after each change, one at a time, in seq order."""
        assert obs.notifier is not None
        while obs.active:
            await obs.dirty.wait()
            obs.dirty.clear()
            async with self._slots:
                response = await self._call(obs.request)
            if not obs.active:
                return
            if obs.quiet and obs.last is not None and _same_answer(response, obs.last):
                continue  # the change did not change this answer (its ETag may have)
            obs.last = response
            obs.seq += 1
            if not await obs.notifier.notify(response, obs.seq):
                self._stop(obs)
                return
            if not response.status.is_success:  # RFC 7641: an error ends the observation
                self._stop(obs)

    def deregister(self, client: Hashable, key: Hashable) -> None:
        """The client ended its observation ``key`` (unknown ones are ignored)."""
        if (obs := self._by_client.get(client, {}).get(key)) is not None:
            self._stop(obs)

    def forget_client(self, client: Hashable) -> None:
        """End every observation of ``client``: it is gone."""
        for obs in list(self._by_client.get(client, {}).values()):
            self._stop(obs)

    def stop_all(self) -> None:
        """End every observation (the server is closing)."""
        for per in list(self._by_client.values()):
            for obs in list(per.values()):
                self._stop(obs)

    def _stop(self, obs: _Observation) -> None:
        if not obs.active:
            return
        obs.active = False
        per = self._by_client.get(obs.client)
        if per is not None and per.get(obs.key) is obs:
            del per[obs.key]
            if not per:
                del self._by_client[obs.client]
        if obs.unsubscribe is not None:
            try:
                obs.unsubscribe()
            except Exception:  # noqa: BLE001 - a service's hook is its own code: the server goes on
                self._log.exception("cancelling the subscription to %r raised", obs.request.path)
        if obs.notifier is not None:
            obs.notifier.close()
        if obs.worker is not None and obs.worker is not asyncio.current_task():
            obs.worker.cancel()


def _same_answer(a: Response, b: Response) -> bool:
    return (a.status, a.content_format, a.payload) == (b.status, b.content_format, b.payload)


# =========================================================================== client side


class ObserverState:
    """The observing client's view of one observation, from its first answer on.

    Registered if that answer carried a ``seq`` and was a success.  A later
    delivery is news only with a higher ``seq`` than the last one (others are
    stale, or not an update of this observation); an error ends it."""

    def __init__(self, response: Response, seq: int | None) -> None:
        self.registered = seq is not None and response.status.is_success
        self.last = seq

    def delivered(self, item: _T | TransportError) -> _T:
        """``item`` from the notification queue, or the :class:`TransportError`
        a closing client queued raised (the observation is then over)."""
        if isinstance(item, TransportError):
            self.registered = False
            raise item
        return item

    def accept(self, response: Response, seq: int | None) -> bool:
        """Whether to deliver ``response`` to the reader."""
        if seq is None or (self.last is not None and seq <= self.last):
            return False
        self.last = seq
        if not response.status.is_success:
            self.registered = False  # the server has ended it
        return True


def put_latest(queue: asyncio.Queue[Any], item: Any) -> None:
    """Enqueue, dropping the oldest item if full: observers want the newest state."""
    if queue.full():
        queue.get_nowait()
    queue.put_nowait(item)
