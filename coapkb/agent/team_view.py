"""What a robot (or the task feeder) knows of the team's states: pushed by
Observe (RFC 7641) on each robot's state resource, never polled."""

from __future__ import annotations

import asyncio
import logging
from typing import Callable, Mapping

from ..messages import ContentFormat, Method, Request
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
    re-registered whenever it ends (robot not up yet, restarted, or lost)."""

    def __init__(self, transport: ClientTransport, endpoints: Mapping[str, Endpoint], path: str) -> None:
        self._transport = transport
        self._endpoints = dict(endpoints)
        self._request = Request(Method.GET, path, accept=ContentFormat.CBOR)
        self.states: States = {}
        self._changed = asyncio.Condition()
        self._watchers: list[asyncio.Task] = []

    def start(self) -> None:
        self._watchers = [
            asyncio.create_task(self._watch(robot_id, endpoint), name=f"observe-{robot_id}")
            for robot_id, endpoint in self._endpoints.items()
        ]

    async def aclose(self) -> None:
        for watcher in self._watchers:
            watcher.cancel()
        await asyncio.gather(*self._watchers, return_exceptions=True)

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
                    async with self._changed:
                        self.states[robot_id] = state
                        self._changed.notify_all()
            except TransportError as exc:
                log.debug("observing %s: %s", robot_id, exc)
            # Not up yet, or the observation ended: register again shortly.
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2, 2.0)

    async def wait(self, predicate: Callable[[States], bool], timeout: float) -> States:
        """Wait until ``predicate(states)`` holds; TimeoutError after ``timeout`` s."""
        async with asyncio.timeout(timeout):
            async with self._changed:
                await self._changed.wait_for(lambda: predicate(self.states))
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
