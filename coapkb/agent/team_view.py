"""What this robot knows of its teammates' planned states: pushed to it by
Observe (RFC 7641) on each teammate's ``/robot/plan``, never polled."""

from __future__ import annotations

import asyncio
import logging
from typing import Mapping

from ..messages import ContentFormat, Method, Request
from ..transport.base import ClientTransport, Endpoint, TransportError
from .robot_state import PlannedState, RobotState

log = logging.getLogger(__name__)

STATE_PATH = "/robot/state"
PLAN_PATH = "/robot/plan"


class TeamView:
    def __init__(self, own: RobotState, teammates: Mapping[str, Endpoint], transport: ClientTransport) -> None:
        self._own = own
        self._peers = dict(teammates)
        self._transport = transport
        self._states: dict[str, RobotState] = {}
        self._changed = asyncio.Condition()
        self._watchers: list[asyncio.Task] = []

    @property
    def own(self) -> RobotState:
        return self._own

    def set_own(self, state: RobotState) -> None:
        self._own = state

    def states(self) -> dict[str, RobotState]:
        return {**self._states, self._own.robot_id: self._own}

    def start(self) -> None:
        for robot_id, endpoint in self._peers.items():
            self._watchers.append(asyncio.create_task(self._watch(robot_id, endpoint), name=f"observe-{robot_id}"))

    async def aclose(self) -> None:
        for watcher in self._watchers:
            watcher.cancel()
        await asyncio.gather(*self._watchers, return_exceptions=True)

    async def _watch(self, robot_id: str, endpoint: Endpoint) -> None:
        """Keep one observation of a teammate alive, re-registering after failures."""
        request = Request(Method.GET, PLAN_PATH, accept=ContentFormat.CBOR)
        backoff = 0.2
        while True:
            try:
                async for response in self._transport.observe(endpoint, request):
                    if not response.status.is_success:
                        log.warning("%s answered %s on %s", robot_id, response.status.dotted, PLAN_PATH)
                        break
                    try:
                        state = RobotState.decode(response.payload)
                    except ValueError as exc:
                        log.warning("bad state from %s: %s", robot_id, exc)
                        continue
                    backoff = 0.2
                    async with self._changed:
                        self._states[robot_id] = state
                        self._changed.notify_all()
            except TransportError as exc:
                log.debug("observing %s: %s", robot_id, exc)
            # Not up yet, or the observation ended: register again shortly.
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2, 2.0)

    async def planned_states(self, seq: int, timeout: float) -> dict[str, PlannedState]:
        """Every team member's planned state right after task ``seq``; waits for
        teammates that have not decided it yet, for at most ``timeout`` seconds."""

        def ready() -> bool:
            return all(s.plan_at(seq) is not None for s in self._states.values()) and set(self._states) >= set(
                self._peers
            )

        try:
            async with asyncio.timeout(timeout):
                async with self._changed:
                    await self._changed.wait_for(ready)
        except TimeoutError:
            missing = sorted(
                r for r in self._peers if r not in self._states or self._states[r].plan_at(seq) is None
            )
            raise TransportError(
                f"no state for task {seq} from {', '.join(missing)} within {timeout:g}s"
            ) from None
        plans = {r: s.plan_at(seq) for r, s in self._states.items()}
        own = self._own.plan_at(seq)
        if own is None:
            raise TransportError(f"own state for task {seq} is gone")
        plans[self._own.robot_id] = own
        return {r: p for r, p in plans.items() if p is not None}
