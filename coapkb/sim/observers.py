"""Observers of the written knowledge, as ``coapkb query --observe`` runs,
and the oracle that none stays silently stale.

An observation can go quiet without an error: the robot observed was
killed and restarted (its new process knows no observer), or it dropped
the observation after a confirmable notification went unacknowledged
(RFC 7641 section 4.5), or the notification of the last change was lost.
The client must notice the silence once the answer's Max-Age has passed
and register again (section 3.3.1); one that trusts the silence prints an
old answer for good.

With ``--observers N`` (and ``--writes``) each of N observer processes
observes the operator's write log of one module at one of its holders,
both drawn by the seed, through :meth:`~coapkb.kb.client.KBClient.observe`
(what the CLI runs), and keeps the last answer it was given.  At the end,
once the replicas agree, the observer of a robot that runs must show what
that robot's KB shows within :data:`OBSERVER_SETTLE_S`.
"""

from __future__ import annotations

import asyncio
import random
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

from ..kb.client import KBClient, QueryFailed, sparql_request
from ..kb.limits import QueryLimits
from ..kb.live import LiveKB
from ..transport.base import Endpoint, TransportError
from ..transport.observation import FRESHNESS_MARGIN_S, REREGISTER_TIMEOUT_S, Notice
from .loop import Process
from .network import SimNetwork
from .operator import log_query, log_values

_LIMITS = QueryLimits()
#: How long after the replicas agree an observer may still show an older
#: answer (13.5 s).  The last change's notification may be lost: the
#: silence is noticed once a writable KB's Max-Age and the margin have
#: passed, and the registration is sent again; one the robot does not
#: answer is given up after :data:`REREGISTER_TIMEOUT_S`, one it answers
#: 5.03 (a holder still catching up) is tried again after the 5.03's
#: Max-Age; and a second for the registration's round trips on lossy links.
OBSERVER_SETTLE_S = (_LIMITS.live_max_age_s + FRESHNESS_MARGIN_S + REREGISTER_TIMEOUT_S
                     + max(_LIMITS.retry_after_s, _LIMITS.live_max_age_s) + 1.0)
#: A first registration that failed (the robot was down) is tried again after this long.
FIRST_TRY_AGAIN_S = 1.0


@dataclass(frozen=True)
class ObserverView:
    """One observer at the end of a run: what it showed last and what the
    robot it observes shows."""

    observer: str
    robot: str
    module: str
    #: The last answer the observer was given (None: none ever).
    shown: frozenset[int] | None
    #: What the robot's KB shows at the end (None: the robot does not run).
    current: frozenset[int] | None
    #: The re-registrations and losses it noticed, in order.
    notices: tuple[str, ...] = ()
    #: Why its observation ended for good (an error answer), if it did.
    ended: str | None = None


class Observer:
    """One observation of ``module``'s write log at ``robot``, run as a
    user runs ``coapkb query --observe``: started again if its first
    registration fails, ended by an error answer."""

    def __init__(self, name: str, robot: str, module: str, endpoint: Endpoint) -> None:
        self.name = name
        self.robot = robot
        self.module = module
        self._endpoint = endpoint
        self._query = log_query(module)
        self.shown: frozenset[int] | None = None
        self.notices: list[str] = []
        self.ended: str | None = None

    async def run(self, process: Process, network: SimNetwork) -> None:
        client = KBClient(await network.for_process(process).open_client("coap"), timeout=10.0)
        request = sparql_request(self._query)

        def notice(what: Notice) -> None:
            self.notices.append(str(what))
        while True:
            try:
                async for result in client.observe(self._endpoint, request, on_notice=notice):
                    self.shown = log_values(result, self._query)
                return  # not reached: the observation registers again rather than end without an error
            except QueryFailed as exc:
                if exc.response.status.dotted != "5.03":
                    self.ended = f"answered {exc.response.status.dotted} {exc.response.text()}"
                    return
            except TransportError as exc:  # the first registration: the robot is not up
                self.notices.append(f"first registration failed: {exc}")
            # A user runs the command again a moment later.
            await asyncio.sleep(FIRST_TRY_AGAIN_S)

    def view(self, current: frozenset[int] | None) -> ObserverView:
        return ObserverView(self.name, self.robot, self.module, self.shown, current, tuple(self.notices), self.ended)


def draw_observers(count: int, rng: random.Random, holders: Mapping[str, list[str]],
                   endpoint: Callable[[str], Endpoint]) -> list[Observer]:
    """``count`` observers, each of a module drawn from ``holders`` (module
    -> the robots holding it) at one of its holders."""
    observers = []
    for i in range(count):
        module = rng.choice(sorted(m for m, robots in holders.items() if robots))
        robot = rng.choice(holders[module])
        observers.append(Observer(f"observer{i + 1}", robot, module, endpoint(robot)))
    return observers


async def observers_caught_up(observers: Sequence[Observer],
                              running: Callable[[], Mapping[str, Mapping[str, LiveKB]]]) -> None:
    """Wait until each observer of a running robot shows what that robot's
    KB shows, :data:`OBSERVER_SETTLE_S` at most (``running``: module ->
    running robot -> its KB, read as it changes)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + OBSERVER_SETTLE_S

    def behind() -> bool:
        now = running()
        return any((values := current_values(o, now)) is not None and o.shown != values for o in observers)
    while behind() and loop.time() < deadline:  # noqa: ASYNC110 - other processes' state, no event to await
        await asyncio.sleep(0.5)


def views(observers: Sequence[Observer], running: Mapping[str, Mapping[str, LiveKB]]) -> list[ObserverView]:
    """Each observer at the end of a run, beside what its robot shows."""
    return [o.view(current_values(o, running)) for o in observers]


def current_values(observer: Observer, running: Mapping[str, Mapping[str, LiveKB]]) -> frozenset[int] | None:
    """What ``observer``'s robot's KB shows of its module now (``running``:
    module -> running robot -> its KB); None if that robot does not run."""
    live = running.get(observer.module, {}).get(observer.robot)
    if live is None:
        return None
    query = log_query(observer.module)
    return log_values(live.query(query), query)
