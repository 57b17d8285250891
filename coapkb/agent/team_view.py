"""What a robot (or the task feeder) knows of the team's states: pushed by
Observe (RFC 7641) on each robot's state resource, never polled."""

from __future__ import annotations

import asyncio
import logging
from typing import Callable, Mapping

from ..transport.messages import ContentFormat, Method, Request
from ..transport.base import ClientTransport, Endpoint, TransportError
from .robot_state import PlannedState, RobotState

log = logging.getLogger(__name__)

#: Full state: live progress and the last decision (the feeder, people).
STATE_PATH = "/robot/state"
#: Planned state only: all a teammate needs to assign tasks.
PLAN_PATH = "/robot/plan"

States = dict[str, RobotState]


class ObservedStates:
    """The latest state of each robot in ``endpoints``, one observation each,
    re-registered whenever it ends (robot not up yet, restarted, or lost).

    A server drops an observation whose notification it could not deliver,
    and the client is not told (RFC 7641 leaves that to Max-Age).  So a wait
    that sees no progress for ``refresh_s`` asks every robot once with a plain
    GET, and re-registers the observations that turned out to be stale."""

    def __init__(
        self,
        transport: ClientTransport,
        endpoints: Mapping[str, Endpoint],
        path: str,
        *,
        refresh_s: float = 10.0,
        request_timeout_s: float = 10.0,
    ) -> None:
        self._transport = transport
        self._endpoints = dict(endpoints)
        self._request = Request(Method.GET, path, accept=ContentFormat.CBOR)
        self.refresh_s = refresh_s
        self.request_timeout_s = request_timeout_s
        self.states: States = {}
        self.refreshes = 0
        self._changed = asyncio.Condition()
        self._watchers: dict[str, asyncio.Task] = {}

    def start(self) -> None:
        for robot_id in self._endpoints:
            self._start_watch(robot_id)

    def _start_watch(self, robot_id: str) -> None:
        old = self._watchers.get(robot_id)
        if old is not None:
            old.cancel()
        self._watchers[robot_id] = asyncio.create_task(
            self._watch(robot_id, self._endpoints[robot_id]), name=f"observe-{robot_id}"
        )

    async def aclose(self) -> None:
        for watcher in self._watchers.values():
            watcher.cancel()
        await asyncio.gather(*self._watchers.values(), return_exceptions=True)

    async def _update(self, robot_id: str, state: RobotState) -> None:
        async with self._changed:
            self.states[robot_id] = state
            self._changed.notify_all()

    async def refresh(self) -> None:
        """GET every robot's state once; re-observe where the observation missed a change."""
        self.refreshes += 1

        async def one(robot_id: str, endpoint: Endpoint) -> None:
            try:
                response = await self._transport.request(endpoint, self._request, timeout=self.request_timeout_s)
                state = RobotState.decode(response.payload) if response.status.is_success else None
            except (TransportError, ValueError) as exc:
                log.debug("refreshing %s: %s", robot_id, exc)
                return
            if state is not None and state != self.states.get(robot_id):
                log.info("observation of %s missed a change; registering again", robot_id)
                await self._update(robot_id, state)
                self._start_watch(robot_id)

        await asyncio.gather(*(one(r, e) for r, e in self._endpoints.items()))

    async def _watch(self, robot_id: str, endpoint: Endpoint) -> None:
        backoff = 0.2
        while True:
            try:
                async for response in self._transport.observe(endpoint, self._request):
                    if not response.status.is_success:
                        log.warning("%s answered %s on %s", robot_id, response.status.dotted, self._request.path)
                        break
                    try:
                        state = RobotState.decode(response.payload)
                    except ValueError as exc:
                        log.warning("bad state from %s: %s", robot_id, exc)
                        continue
                    backoff = 0.2
                    await self._update(robot_id, state)
            except TransportError as exc:
                log.debug("observing %s: %s", robot_id, exc)
            # Not up yet, or the observation ended: register again shortly.
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2, 2.0)

    async def wait(self, predicate: Callable[[States], bool], timeout: float) -> States:
        """Wait until ``predicate(states)`` holds; TimeoutError after ``timeout`` s."""
        async with asyncio.timeout(timeout):
            while True:
                try:
                    async with asyncio.timeout(self.refresh_s):
                        async with self._changed:
                            await self._changed.wait_for(lambda: predicate(self.states))
                    return dict(self.states)
                except TimeoutError:
                    await self.refresh()
                    if predicate(self.states):
                        return dict(self.states)


class TeamView:
    """This robot's own state plus its teammates' planned states."""

    def __init__(self, own: RobotState, teammates: Mapping[str, Endpoint], transport: ClientTransport) -> None:
        self._own = own
        self._teammates = ObservedStates(transport, teammates, PLAN_PATH)
        self._peers = set(teammates)

    @property
    def own(self) -> RobotState:
        return self._own

    def set_own(self, state: RobotState) -> None:
        self._own = state

    def start(self) -> None:
        self._teammates.start()

    async def aclose(self) -> None:
        await self._teammates.aclose()

    async def planned_states(self, seq: int, timeout: float) -> dict[str, PlannedState]:
        """Every team member's planned state right after task ``seq``; waits for
        teammates that have not decided it yet, for at most ``timeout`` seconds."""

        def ready(states: States) -> bool:
            return set(states) >= self._peers and all(s.plan_at(seq) is not None for s in states.values())

        try:
            states = await self._teammates.wait(ready, timeout)
        except TimeoutError:
            states = self._teammates.states
            missing = sorted(r for r in self._peers if r not in states or states[r].plan_at(seq) is None)
            raise TransportError(f"no state for task {seq} from {', '.join(missing)} within {timeout:g}s") from None
        own = self._own.plan_at(seq)
        if own is None:
            raise TransportError(f"own state for task {seq} is gone")
        plans = {robot_id: state.plan_at(seq) for robot_id, state in states.items()}
        plans[self._own.robot_id] = own
        return {r: p for r, p in plans.items() if p is not None}
