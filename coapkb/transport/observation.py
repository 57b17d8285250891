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

    An answer with a Max-Age is sent again, changed or not, shortly before
    that Max-Age runs out (:func:`refresh_after`): the observer's copy stays
    fresh, and its silence says the server lost the observation.

Client side: :class:`ObserverState` and :func:`put_latest`
    Which notifications are news (a higher ``seq`` than the last one
    delivered) and whether the server still holds the observation; the
    notification queue keeps the newest states when the reader is slow.

Every transport: :func:`observe_fresh`
    An observation that notices when its server lost it (killed, restarted,
    the registration dropped): after Max-Age plus :data:`FRESHNESS_MARGIN_S`
    without a notification it registers again (RFC 7641 section 3.3.1), and
    while the server does not answer it keeps trying, reporting both.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncGenerator, AsyncIterator, Awaitable, Callable, Coroutine, Hashable
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol, TypeVar

from .base import ClientTransport, Endpoint, PeerUnreachable, Service, TransportError, handle_safely
from .messages import Request, Response, Status

__all__ = [
    "Answer",
    "Delivery",
    "FRESHNESS_MARGIN_S",
    "Notice",
    "Notifier",
    "ObservationRegistry",
    "ObserverState",
    "observe_fresh",
    "put_latest",
    "refresh_after",
]

_T = TypeVar("_T")

log = logging.getLogger(__name__)

#: How long before an answer's Max-Age runs out the server sends it again
#: (at most; a quarter of a short Max-Age): the time the refresh has to
#: cross the network before the observer's copy goes stale.
REFRESH_LEAD_S = 0.5
#: What an observer adds to Max-Age before it counts a silent observation as
#: lost.  Max-Age runs from when the server answered, the observer's wait
#: from when the answer arrived: a refresh that left on time still takes its
#: way across the network, and the observer's own loop may run late.  With
#: the server's lead (:data:`REFRESH_LEAD_S`) that is a second of slack, far
#: more than a loopback or LAN round trip, and small beside a Max-Age of 2 s:
#: a lost observation is still noticed within Max-Age and half a second.  A
#: lost refresh (its retransmission comes later) costs one re-registration,
#: the cheap side to err on.
FRESHNESS_MARGIN_S = 0.5
#: Max-Age of an answer that carries none (RFC 7252 section 5.10.5).
DEFAULT_MAX_AGE_S = 60
#: The least silence that counts: Max-Age 0 would re-register after every notification.
MIN_SILENCE_S = 1.0
#: A re-registration without an answer this long counts as failed (tried
#: again): a CoAP registration has been retransmitted by then, and a server
#: that is there answers a registration like any request, in a round trip.
REREGISTER_TIMEOUT_S = 5.0
#: The first wait before trying a lost server again; it doubles up to the
#: answer's Max-Age (no server that kept its observation would have been
#: silent longer), and at most :data:`RETRY_MAX_S`.
RETRY_MIN_S = 0.25
RETRY_MAX_S = 30.0


def refresh_after(max_age: int | None) -> float | None:
    """Seconds after sending an answer with ``max_age`` at which to send it
    again if nothing changed; None: never (no Max-Age, or 0: no freshness promised)."""
    if not max_age:
        return None
    return max_age - min(REFRESH_LEAD_S, max_age / 4)

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
        """Send the current state after each change, one at a time, in seq
        order; and again before the Max-Age of the last one sent runs out."""
        assert obs.notifier is not None
        loop = asyncio.get_running_loop()
        refresh_at = _refresh_at(obs.last, loop.time())
        while obs.active:
            try:
                async with asyncio.timeout_at(refresh_at):
                    await obs.dirty.wait()
                stale = False
            except TimeoutError:
                stale = True
            obs.dirty.clear()
            async with self._slots:
                response = await self._call(obs.request)
            if not obs.active:
                return
            if not stale and obs.quiet and obs.last is not None and _same_answer(response, obs.last):
                continue  # the change did not change this answer (its ETag may have)
            obs.last = response
            obs.seq += 1
            refresh_at = _refresh_at(response, loop.time())
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


def _refresh_at(sent: Response | None, now: float) -> float | None:
    after = None if sent is None or not sent.status.is_success else refresh_after(sent.max_age)
    return None if after is None else now + after


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


# =========================================================================== every transport


@dataclass(frozen=True)
class Notice:
    """What happened to an observation itself, not to what it observes:
    ``re-registered`` (registered again, and why) or ``lost`` (the server
    does not answer; it is tried again).  ``str()`` is one line for a person."""

    kind: Literal["re-registered", "lost"]
    line: str

    def __str__(self) -> str:
        return self.line


def _silence_limit(max_age: int) -> float:
    return max(float(max_age), MIN_SILENCE_S) + FRESHNESS_MARGIN_S


def _why(exc: Exception, peer: Endpoint) -> str:
    """``exc``'s text without the peer the line names already."""
    text = str(exc) or type(exc).__name__
    for prefix in (f"no answer from {peer}: ", f"{peer}: "):
        if text.startswith(prefix):
            return text[len(prefix):]
    return text


def _try_later(response: Response) -> bool:
    """5.03: the server is there but cannot answer now (Max-Age: when to ask again)."""
    return response.status == Status.SERVICE_UNAVAILABLE


class _FreshObservation:
    """What :func:`observe_fresh` knows between one answer and the next: the
    last answer yielded, its Max-Age and when it came, why the next
    registration is one again, and since when (and how patiently) a server
    that does not answer is tried again."""

    def __init__(self, peer: Endpoint, request: Request, on_notice: Callable[[Notice], None] | None) -> None:
        self.peer = peer
        self.request = request
        self.tell = on_notice if on_notice is not None else (lambda notice: log.info("%s %s: %s", peer, request.path, notice))
        self.loop = asyncio.get_running_loop()
        self.last: Response | None = None  # the last answer yielded
        self.max_age = DEFAULT_MAX_AGE_S
        self.heard = 0.0  # when the last answer came
        self.why = ""  # why the next registration is a re-registration
        self.lost_since: float | None = None
        self.retry = RETRY_MIN_S

    async def lost(self, reason: str, wait_s: float = 0.0) -> None:
        """Tell of the loss (once, until the server answers again), then wait to try again."""
        if self.lost_since is None:
            self.lost_since = self.loop.time()
            self.tell(Notice("lost", f"lost {self.peer}: {reason}; retrying"))
        await asyncio.sleep(max(self.retry, wait_s))  # a timed retry: nothing to wait on but the clock
        self.retry = min(self.retry * 2, max(RETRY_MIN_S, min(float(self.max_age), RETRY_MAX_S)))

    async def registration(self, stream: AsyncIterator[Response]) -> Response | None:
        """The registration's answer (the first, or again); None once a failed
        re-registration's retry has been waited out.  A first registration that
        ends unanswered, or finds the peer unreachable, raises to the caller."""
        first = self.last is None
        try:
            if first:
                response = await anext(stream)
            else:
                async with asyncio.timeout(REREGISTER_TIMEOUT_S):
                    response = await anext(stream)
        except StopAsyncIteration:
            if first:
                raise TransportError(f"{self.peer} did not answer the observation of {self.request.path}") from None
            await self.lost("it ended the observation without an answer")
            return None
        except TimeoutError:
            await self.lost(f"no answer within {REREGISTER_TIMEOUT_S:g} s")
            return None
        except PeerUnreachable as exc:
            if first:
                raise
            await self.lost(_why(exc, self.peer))
            return None
        self.heard = self.loop.time()
        if not first:
            if _try_later(response):
                await self.lost(f"answered {response.status.dotted} {response.text()}", float(response.max_age or 0))
                return None
            if self.lost_since is not None:
                self.why = f"{self.peer} answers again, after {self.heard - self.lost_since:.1f} s"
            self.tell(Notice("re-registered", f"re-registered: {self.why}"))
        self.lost_since, self.retry = None, RETRY_MIN_S
        self.max_age = DEFAULT_MAX_AGE_S if response.max_age is None else response.max_age
        return response

    async def notification(self, stream: AsyncIterator[Response]) -> Response | None:
        """The next notification, within Max-Age of the answer before; None
        when the observation is to be registered again (``why`` says why)."""
        try:
            async with asyncio.timeout_at(self.heard + _silence_limit(self.max_age)):
                response = await anext(stream)
        except TimeoutError:
            self.why = f"no notification within Max-Age {self.max_age} s"
            return None
        except StopAsyncIteration:
            # Ended without an error: the server kept no observation
            # (no slot left) or closed.  Ask again once the answer is stale.
            await asyncio.sleep(max(self.heard + _silence_limit(self.max_age) - self.loop.time(), 0.0))
            self.why = f"{self.peer} ended the observation"
            return None
        except PeerUnreachable as exc:
            self.why = _why(exc, self.peer)
            return None
        self.heard = self.loop.time()
        if _try_later(response):
            self.why = f"{self.peer} answered {response.status.dotted} {response.text()}"
            await asyncio.sleep(float(response.max_age or 0))  # the server said when to ask again
            return None
        self.max_age = DEFAULT_MAX_AGE_S if response.max_age is None else response.max_age
        return response

    def is_news(self, response: Response) -> bool:
        """Whether ``response`` differs from the last answer yielded; if so it becomes that answer."""
        if self.last is not None and _same_answer(response, self.last):
            return False
        self.last = response
        return True


async def observe_fresh(
    transport: ClientTransport,
    peer: Endpoint,
    request: Request,
    *,
    on_notice: Callable[[Notice], None] | None = None,
) -> AsyncGenerator[Response, None]:
    """``transport.observe(peer, request)`` that notices when it went silent.

    Yields the first answer, then each notification whose answer differs
    from the last one yielded (a server's refresh of an unchanged answer is
    not news).  If Max-Age (60 s when absent) plus :data:`FRESHNESS_MARGIN_S`
    passes without a notification -- the server was killed or restarted, or
    dropped the observation -- it registers again (RFC 7641 section 3.3.1:
    the server lost track, or the notifications do; a new registration
    answers the current state either way, and its answer is yielded if it
    differs).  A registration that is not answered (the server is gone, or
    silent for :data:`REREGISTER_TIMEOUT_S`), or answered 5.03, is tried
    again, the waits doubling from :data:`RETRY_MIN_S` up to the answer's
    Max-Age, so a server back up is registered with again within Max-Age of
    it serving.  Each re-registration and each loss (once, until the server
    answers again) is told to ``on_notice`` (default: logged).

    The first registration is the transport's: its errors
    (:class:`PeerUnreachable`, ...) are the caller's, as is any
    :class:`TransportError` other than an unreachable peer (a closed
    transport).  An error answer (other than 5.03) is yielded and ends the
    iteration, as it ends the observation (RFC 7641).
    """
    fresh = _FreshObservation(peer, request, on_notice)
    while True:
        stream = transport.observe(peer, request)
        try:
            # The registration's answer, then each notification; None: register again.
            response = await fresh.registration(stream)
            while response is not None:
                if fresh.is_news(response):
                    yield response
                if not response.status.is_success:
                    return
                response = await fresh.notification(stream)
        finally:
            # Deregisters where the transport can (an async generator, typed an AsyncIterator).
            close: Callable[[], Awaitable[None]] | None = getattr(stream, "aclose", None)
            if close is not None:
                await close()
