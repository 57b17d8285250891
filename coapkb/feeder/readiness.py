"""Whether the robots can be fed, asked once before the first task: each
must answer, be done with earlier tasks (another feeder's), and have taken
the same tasks as the rest of its cluster; this feeder's tasks follow on
from theirs."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Mapping

from ..agent.robot_state import RobotState
from ..transport.base import TransportError
from .channel import Channel
from .membership import Membership
from .tasks import FeederError

log = logging.getLogger(__name__)


def _last_task(state: RobotState) -> int:
    """The number of the last task ``state``'s robot took and decided (0: none)."""
    return max(state.plan.seq, state.last.seq if state.last is not None else 0)


async def check_ready(channel: Channel, membership: Membership, timeout: float,
                      hints: Mapping[str, str] | None = None) -> dict[int, int]:
    """Ask every robot once for its state, within ``timeout`` seconds;
    cluster index -> the number of its first task for this feeder.
    ``hints``: robot -> what to do about one that does not answer, added
    to the error.  A robot started again by hand joins its teammates at
    that task (``membership``'s rejoin); robots of a cluster at different
    tasks otherwise are refused."""

    async def ask(robot_id: str) -> RobotState | str:
        """``robot_id``'s state, or why it cannot be fed."""
        endpoint = channel.endpoint(robot_id)
        try:
            response = await channel.client.request(endpoint, channel.settings.watch_request, timeout=timeout)
        except TransportError as exc:
            hint = f"; {hints[robot_id]}" if hints and robot_id in hints else ""
            return f"{robot_id} does not answer at {endpoint} ({exc}){hint}"
        try:
            state = RobotState.decode(response.payload) if response.status.is_success else None
        except ValueError:
            state = None
        if state is None:
            return f"{robot_id} at {endpoint} answered {response.status.dotted}, not its state"
        if state.live.activity != "idle" or state.live.queued:
            return f"{robot_id} is still executing earlier tasks: feed it once it is idle"
        return state

    # Every robot asked to the end: one line names them all, and no request is left behind.
    robots = channel.roster.robot_ids
    answers = await asyncio.gather(*(ask(r) for r in robots))
    problems = [a for a in answers if isinstance(a, str)]
    if problems:
        raise FeederError("; ".join(problems))
    states = {r: a for r, a in zip(robots, answers) if isinstance(a, RobotState)}
    first_seq: dict[int, int] = {}
    for index, cluster in enumerate(channel.roster.clusters):
        taken = {r: _last_task(states[r]) for r in cluster}
        # A robot started again by hand: a new process that has taken no
        # task while its teammates took some.  It joins them at this
        # feeder's first task, as a robot restarted during a run does
        # (its teammates tell the new process by its boot and admit it
        # there).  Robots at different tasks otherwise are refused.
        fresh = [r for r, n in taken.items() if n == 0 and not states[r].live.done]
        went_on = {n for r, n in taken.items() if r not in fresh}
        if fresh and len(went_on) == 1 and went_on != {0}:
            for robot_id in fresh:
                log.warning("%s started again by hand: it joins its teammates at task %d",
                            robot_id, max(went_on) + 1)
                await membership.rejoin(robot_id)
        elif len(set(taken.values())) > 1:
            raise FeederError(f"the robots of cluster {index + 1} have taken different tasks "
                              f"({', '.join(f'{r}: up to {n}' for r, n in taken.items())}): restart them")
        first_seq[index] = max(taken.values(), default=0) + 1
    for robot_id, state in states.items():
        membership.set_done_before(robot_id, state.live.done)
    return first_seq
