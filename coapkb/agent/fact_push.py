"""Facts pushed by their holder before a teammate asks for them.

Every robot of a cluster needs the same facts for a task (compute by all),
and each one that lacks a KB module asked its holder for them: a request
and an answer per robot and fact.  The holder needs them too, at the same
moment, and runs the same named queries on its own KB; so it publishes each
answer it gives itself for a task on ``/kb/facts/MODULE``, and the
teammates that read that module from it observe that resource (RFC 7641,
NON notifications like ``/robot/plan``).  The Query Handler waits for a
pushed answer a bounded time (about two round trips) before it asks, and
puts it in its answer cache (:meth:`KBClient.prime`) as if its request had
just been answered: a lost notification costs a query, never a wrong answer.

:class:`FactPusher` is the holder's side, :class:`PushedFacts` the
teammate's.  The representation is ``robot-facts`` (docs/robot-state.cddl):
the answers the holder has given for its latest task, so a notification
that replaces another still carries the answers of both.
"""

from __future__ import annotations

import asyncio
import collections
import logging
from collections import OrderedDict
from collections.abc import Awaitable, Callable, Mapping

from .. import clock
from ..cancelling import cancel_and_wait
from ..kb.client import DEFAULT_MAX_AGE_S
from ..transport.base import ClientTransport, Endpoint, PeerGone, ResourceInfo, TransportError
from ..transport.messages import ContentFormat, Method, Request, Response, Status
from ..transport.router import Router
from ..wire.codec import CodecError
from ..wire.pushed import MAX_PUSHED, PushedAnswer, decode_pushed, encode_pushed, request_key

log = logging.getLogger(__name__)

FACTS_PATH = "/kb/facts"
#: Answers remembered: pushed (holder), arrived or awaited (teammate).
ANSWERS_KEPT = 256
#: Arrival times kept per named query, and how many before they set the wait.
LATENESS_KEPT = 32
LATENESS_SAMPLES_MIN = 4
#: Waits in a row for one holder that run out before its observation is registered again.
MISSES_BEFORE_REREGISTERING = 3
#: An answer pushed before is pushed again this long before its Max-Age
#: runs out: the teammates that took it then still hold it until then.
REPUSH_MARGIN_S = 1.0


def facts_path(module: str) -> str:
    """Where a holder pushes its answers from ``module``."""
    return f"{FACTS_PATH}/{module}"


class FactPusher:
    """A holder's answers for its latest task, one observable resource per
    module it holds; ``ready``: until the holder may answer reads (a
    restarted holder catching up), as its queries wait."""

    def __init__(self, router: Router, modules: tuple[str, ...],
                 ready: Callable[[], Awaitable[None]] | None = None) -> None:
        self._router = router
        self._ready = ready
        self._task = 0
        self._answers: dict[str, OrderedDict[bytes, PushedAnswer]] = {module: OrderedDict() for module in modules}
        #: Request key -> (the result pushed, until when teammates hold it).
        self._held: OrderedDict[bytes, tuple[bytes, float]] = OrderedDict()
        self._dirty: set[str] = set()
        self._notifying: asyncio.Handle | None = None
        for module in modules:
            router.add(ResourceInfo(facts_path(module), rt="coapkb.facts", ct=(60,), obs=True,
                                    title=f"answers from the {module} KB for the latest task"), self._get)

    def begin(self, task: int) -> None:
        """The holder starts deciding ``task``: the answers of the one before are not pushed again."""
        if task != self._task:
            self._task = task
            for answers in self._answers.values():
                answers.clear()

    async def offer(self, module: str, name: str, params: Mapping[str, str]) -> None:
        """Publish the answer this robot's KB gives ``/kb/q/NAME?params`` now,
        exactly as its resource answers a teammate that asks, unless the
        teammates still hold the same answer from an earlier push."""
        answers = self._answers.get(module)
        if answers is None:
            return
        response = await self._router.handle(Request(Method.GET, f"/kb/q/{name}", dict(params),
                                                     accept=ContentFormat.CBOR))
        if response.status != Status.CONTENT or response.content_format != ContentFormat.CBOR:
            return
        key, now = request_key(name, params), clock.monotonic()
        held = self._held.get(key)
        if key in answers or (held is not None and held[0] == response.payload and now < held[1]):
            return
        max_age = DEFAULT_MAX_AGE_S if response.max_age is None else response.max_age
        self._held[key] = (response.payload, now + max_age - REPUSH_MARGIN_S)
        self._held.move_to_end(key)
        while len(self._held) > ANSWERS_KEPT:
            self._held.popitem(last=False)
        answers[key] = PushedAnswer(key, response.max_age, response.payload)
        while len(answers) > MAX_PUSHED:
            answers.popitem(last=False)
        # One notification for the answers given in one turn of the loop
        # (the layout, the docks and the energy figures come together).
        if not self._dirty:
            self._notifying = asyncio.get_running_loop().call_soon(self._notify)
        self._dirty.add(module)

    def close(self) -> None:
        """Drop a notification still due this turn: the server is closing."""
        if self._notifying is not None:
            self._notifying.cancel()
        self._dirty.clear()

    def _notify(self) -> None:
        self._notifying = None
        dirty, self._dirty = self._dirty, set()
        for module in sorted(dirty):
            self._router.notify(facts_path(module))

    async def _get(self, request: Request) -> Response:
        # A read of the module like a query: a restarted holder answers a
        # teammate registering only once caught up (found in the simulator,
        # seed 59 of the catch-up profile: the registration answered while
        # the holder still lacked four acknowledged values).
        if self._ready is not None:
            await self._ready()
        module = request.path.rsplit("/", 1)[1]
        return Response(Status.CONTENT, encode_pushed(list(self._answers[module].values())), ContentFormat.CBOR)


class _Awaited:
    """One answer a holder pushed, or that a waiter expects of it."""

    def __init__(self) -> None:
        self.arrived = asyncio.Event()
        self.answer: PushedAnswer | None = None
        #: The query's name and when a robot began to wait for it (None: nobody has yet).
        self.name = ""
        self.since: float | None = None


class PushedFacts:
    """A teammate's side: observes ``/kb/facts/MODULE`` at the holder it
    reads each module from, and hands what arrives to whoever waits for it."""

    def __init__(self, transport: ClientTransport, holders: Mapping[str, tuple[str, Endpoint]],
                 on_gone: Callable[[str, Exception], Awaitable[None]] | None = None) -> None:
        """``holders``: module -> (the holder's robot id, its endpoint);
        ``on_gone``: told when a holder that was observed here is found gone
        (nobody listens at its address), for failure detection."""
        self._transport = transport
        self._holders = dict(holders)
        self._on_gone = on_gone
        #: Holders whose observation was registered once: found gone since,
        #: they died (not: were not up yet).
        self._observed: set[Endpoint] = set()
        #: Per holder, set while its observation is registered: only those are waited for.
        self._registered: dict[Endpoint, asyncio.Event] = {}
        self._answers: OrderedDict[tuple[Endpoint, bytes], _Awaited] = OrderedDict()
        self._watchers: dict[str, asyncio.Task[None]] = {}
        #: Waits in a row that ran out, per holder: a holder that restarted
        #: has forgotten its observers, and says nothing (NON notifications).
        self._misses: dict[Endpoint, int] = {}
        #: Answers that arrived pushed, and waits that ran out first.
        self.arrivals = 0
        self.missed = 0
        #: The quickest registration's round trip, seconds (None: none answered yet).
        self.round_trip_s: float | None = None
        #: Per named query, how late its latest awaited answers came (seconds after the wait began).
        self._late: dict[str, collections.deque[float]] = {}

    def start(self) -> None:
        for module in sorted(self._holders):
            self._start_watch(module)

    def _start_watch(self, module: str) -> None:
        old = self._watchers.get(module)
        if old is not None:
            old.cancel()
        robot_id, endpoint = self._holders[module]
        self._registration(endpoint).clear()
        self._watchers[module] = asyncio.create_task(self._watch(module, endpoint), name=f"facts-{robot_id}")

    async def aclose(self) -> None:
        await cancel_and_wait(self._watchers.values())
        self._watchers.clear()

    def expects(self, endpoint: Endpoint) -> bool:
        """Does ``endpoint`` push to this robot now?"""
        registered = self._registered.get(endpoint)
        return registered is not None and registered.is_set()

    async def observing(self, endpoint: Endpoint) -> None:
        """Until ``endpoint`` pushes to this robot (its observation registered)."""
        await self._registration(endpoint).wait()

    def _registration(self, endpoint: Endpoint) -> asyncio.Event:
        return self._registered.setdefault(endpoint, asyncio.Event())


    async def wait(self, endpoint: Endpoint, name: str, params: Mapping[str, str],
                   within: float) -> PushedAnswer | None:
        """``endpoint``'s pushed answer to ``name`` with ``params``, waited
        for at most ``within`` seconds; None if it has not come by then."""
        awaited = self._awaited((endpoint, request_key(name, params)))
        if awaited.since is None:
            awaited.name, awaited.since = name, clock.monotonic()
            if awaited.arrived.is_set():
                self._lateness(name).append(0.0)
        if not awaited.arrived.is_set():
            try:
                async with asyncio.timeout(within):
                    await awaited.arrived.wait()
            except TimeoutError:
                self._missed(endpoint)
                return None
        self._misses[endpoint] = 0
        return awaited.answer

    def _missed(self, endpoint: Endpoint) -> None:
        self.missed += 1
        self._misses[endpoint] = self._misses.get(endpoint, 0) + 1
        if self._misses[endpoint] >= MISSES_BEFORE_REREGISTERING:
            self._misses[endpoint] = 0
            for module, (_, holder) in self._holders.items():
                if holder == endpoint:
                    self._start_watch(module)

    def _awaited(self, key: tuple[Endpoint, bytes]) -> _Awaited:
        awaited = self._answers.get(key)
        if awaited is None:
            awaited = self._answers[key] = _Awaited()
            while len(self._answers) > ANSWERS_KEPT:
                self._answers.popitem(last=False)
        return awaited

    async def _watch(self, module: str, endpoint: Endpoint) -> None:
        request = Request(Method.GET, facts_path(module), accept=ContentFormat.CBOR)
        backoff = 0.2
        while True:
            registered = clock.monotonic()
            try:
                async for response in self._transport.observe(endpoint, request):
                    if not self.expects(endpoint):  # the registration's answer
                        took = clock.monotonic() - registered
                        self.round_trip_s = took if self.round_trip_s is None else min(self.round_trip_s, took)
                    if not response.status.is_success:
                        log.debug("%s answered %s on %s", endpoint, response.status.dotted, request.path)
                        break
                    self._registration(endpoint).set()
                    self._observed.add(endpoint)
                    backoff = 0.2
                    self._take(endpoint, response.payload)
            except TransportError as exc:
                log.debug("observing %s of %s: %s", request.path, endpoint, exc)
                if endpoint in self._observed and isinstance(exc, PeerGone) and self._on_gone is not None:
                    # Counted like a failed query: a holder that died between
                    # two tasks was otherwise found down only by a wait for
                    # its plan, and if it had restarted meanwhile, cut off,
                    # only after a request timeout (simulator seed 1567 of
                    # the rejoin profile: a second teammate died within it,
                    # and the survivor, outnumbered, decided nothing).
                    await self._on_gone(self._holders[module][0], exc)
            self._registration(endpoint).clear()
            # Not up yet, restarted, or the observation ended: register again shortly.
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2, 5.0)

    def _take(self, endpoint: Endpoint, payload: bytes) -> None:
        try:
            answers = decode_pushed(payload)
        except CodecError as exc:
            log.warning("bad pushed answers from %s: %s", endpoint, exc)
            return
        for answer in answers:
            awaited = self._awaited((endpoint, answer.key))
            if not awaited.arrived.is_set():
                self.arrivals += 1
                awaited.answer = answer
                awaited.arrived.set()
                if awaited.since is not None:  # awaited: how late it came (if after the wait ran out, too)
                    self._lateness(awaited.name).append(clock.monotonic() - awaited.since)

    def _lateness(self, name: str) -> collections.deque[float]:
        return self._late.setdefault(name, collections.deque(maxlen=LATENESS_KEPT))

    def expected_within(self, name: str) -> float | None:
        """How long ``name``'s pushed answers usually take to come once a robot
        needs them: half as much again as the latest ones' 90th percentile
        (None: too few awaited yet).  Answers that need another holder's fact
        first (the grip) come a round trip later than the rest, so each query
        has its own; until it has a few, every query's together stand in (a
        short shift asks most queries only a few times)."""
        late = sorted(self._late.get(name, ()))
        if len(late) < LATENESS_SAMPLES_MIN:
            late = sorted(t for times in self._late.values() for t in times)
            if len(late) < LATENESS_SAMPLES_MIN:
                return None
        return 1.5 * late[min(len(late) - 1, int(0.9 * len(late)))]
