"""The fence before a down robot's tasks go round again: every survivor of
its cluster says it no longer grants the robot a lease, and the feeder
waits the lease out (docs/failover.md, "The fence"); or, if they still
grant it (it came back), the wait until it has done what it holds."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Sequence

from .. import clock
from ..agent.lease import LEASE_PATH
from ..agent.robot_state import RobotState
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


async def settle(channel: Channel, robot_id: str, through: int | None = None) -> None:
    """Wait until ``robot_id`` (down for the feeder, but its teammates
    still grant it: it came back) has decided every task up to
    ``through`` (one it was just given again) and executed what it holds,
    so its statistics in the record are final.  Each state observed is
    kept: the watcher no longer watches a down robot, and what the robot
    did meanwhile (its ``done`` count, the tasks it dropped under its
    fence) decides which of its tasks go round again.  Found in the simulator: a robot cut off
    dropped a task under its fence, its teammates granted it again once the
    partition healed, and the task, never seen dropped, was lost."""
    watcher = channel.watcher
    known = watcher.states.get(robot_id)

    def settled(state: RobotState) -> bool:
        """Kept; True once there is nothing more to wait for."""
        if known is not None and state.boot != known.boot:
            return True  # another process: a restart, which joins at a task boundary
        watcher.states[robot_id] = state
        decided = through is None or state.plan.seq >= through
        return decided and state.live.activity == "idle" and state.live.queued == 0

    loop = asyncio.get_running_loop()
    deadline = loop.time() + channel.settings.task_timeout_s * 4
    with contextlib.suppress(TransportError, ValueError):
        while loop.time() < deadline:
            # A notification later than the watcher's refresh time is asked
            # for, and the observation registered again: its server drops
            # it after a confirmable notification goes unacknowledged (RFC
            # 7641 4.5), as Robot8's did while the feeder was cut off
            # (seed 1891 of the nine-robot freeze and partition profile:
            # the feeder then waited out 480 s).
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(min(watcher.refresh_s, deadline - loop.time())) as quiet:
                    watch = channel.settings.watch_request
                    async for response in channel.client.observe(channel.endpoint(robot_id), watch):
                        if settled(RobotState.decode(response.payload)):
                            return
                        quiet.reschedule(min(loop.time() + watcher.refresh_s, deadline))
            state = await channel.state(robot_id, channel.settings.query_timeout_s)
            if state is not None and settled(state):
                return
