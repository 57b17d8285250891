"""The fence before a down robot's tasks go round again: every survivor of
its cluster says it no longer grants the robot a lease, and the feeder
waits the lease out (docs/failover.md, "The fence")."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Sequence

from .. import clock
from ..agent.lease import LEASE_PATH
from ..transport.base import TransportError
from ..transport.messages import Method, Request, Status
from .channel import Channel
from .tasks import FeederError

log = logging.getLogger(__name__)


async def fence(channel: Channel, cluster: Sequence[str], robot_id: str) -> bool:
    """Before down ``robot_id``'s tasks go round again: ask every survivor
    of its cluster whether it still grants it a lease (each probes it
    first), then wait the lease out from the last refusal.  False if a
    survivor still grants it (it answers them: its tasks stay its own)."""
    watcher = channel.watcher
    lease_s = channel.settings.lease_s
    if lease_s <= 0:
        return True
    request = Request(Method.GET, LEASE_PATH, {"r": robot_id, "check": ""})

    async def refused_at(survivor: str) -> float | None:
        """When ``survivor`` said it no longer grants ``robot_id`` (now if it is down).
        A survivor neither answering nor found down (the feeder cut off
        itself) is asked again until the task timeout, as a task's wait."""
        deadline = clock.monotonic() + channel.settings.task_timeout_s
        while survivor not in watcher.down:
            try:
                response = await channel.client.request(
                    channel.endpoint(survivor), request, timeout=channel.settings.task_timeout_s
                )
            except TransportError as exc:
                await watcher.probe(survivor)
                if survivor not in watcher.down and clock.monotonic() > deadline:
                    raise FeederError(f"{survivor} did not say whether it grants {robot_id} a lease "
                                      f"within {channel.settings.task_timeout_s:g}s: {exc}") from None
                continue
            if response.status == Status.FORBIDDEN:
                return clock.monotonic()
            if response.status.is_success:
                return None
            raise FeederError(
                f"{survivor} answered {response.status.dotted} about {robot_id}'s lease: {response.text()}"
            )
        return clock.monotonic()

    survivors = [r for r in cluster if r != robot_id and r not in watcher.down]
    answers = await asyncio.gather(*(refused_at(r) for r in survivors))
    if any(at is None for at in answers):
        granting = [r for r, at in zip(survivors, answers) if at is None]
        log.warning("%s still grant %s a lease: its tasks stay with it", ", ".join(granting), robot_id)
        return False
    # Waiting the lease out is the fence itself: any lease the robot
    # holds was granted before the last refusal, so it ends within this.
    last = max((at for at in answers if at is not None), default=clock.monotonic())
    await asyncio.sleep(max(0.0, last + lease_s - clock.monotonic()))
    # From now on the robot can pick nothing: if it answers (it was only
    # cut off), its state is final and says what it did pick.
    state = await channel.state(robot_id, watcher.request_timeout_s)
    known = watcher.states.get(robot_id)
    if state is not None and known is not None and state.boot == known.boot:
        watcher.states[robot_id] = state
    log.warning("%s's lease has run out: its unexecuted tasks go round again", robot_id)
    return True
