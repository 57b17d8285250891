"""ObservedStates recovers from an observation the server dropped silently."""

from __future__ import annotations

import asyncio
from typing import AsyncIterator

from coapkb.agent.robot_state import LiveState, PlannedState, RobotState
from coapkb.agent.team_view import PLAN_PATH, ObservedStates
from coapkb.transport.messages import ContentFormat, Request, Response, Status
from coapkb.transport.base import Endpoint, TrafficCounters


def state(seq: int) -> RobotState:
    return RobotState("Robot2", PlannedState(1, 0, 400.0, 0.0, 30.0, seq), LiveState(1.0, 0.0))


class SilentlyDroppedObservation:
    """Observe yields the first state, then nothing (the server dropped the
    observation); a plain GET already sees the robot's newer state."""

    def __init__(self) -> None:
        self.counters = TrafficCounters()
        self.current = state(0)
        self.observations = 0

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        return Response(Status.CONTENT, self.current.encode_plan(), ContentFormat.CBOR)

    async def observe(self, peer: Endpoint, request: Request) -> AsyncIterator[Response]:
        self.observations += 1
        yield Response(Status.CONTENT, self.current.encode_plan(), ContentFormat.CBOR)
        await asyncio.Event().wait()  # no notification ever again

    async def aclose(self) -> None:
        pass


async def test_a_stale_observation_is_refreshed_and_registered_again() -> None:
    transport = SilentlyDroppedObservation()
    states = ObservedStates(transport, {"Robot2": Endpoint("coap", "127.0.0.1", 1)}, PLAN_PATH, refresh_s=0.1)
    states.start()
    try:
        await states.wait(lambda s: "Robot2" in s, timeout=2)
        transport.current = state(1)  # decided task 1; the notification never comes
        seen = await states.wait(lambda s: s["Robot2"].plan.seq >= 1, timeout=2)
        assert seen["Robot2"].plan.seq == 1
        assert states.refreshes >= 1
        await asyncio.sleep(0)  # let the new watcher register
        assert transport.observations == 2
    finally:
        await states.aclose()
