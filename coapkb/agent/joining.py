"""Where a restarted robot joins its cluster: the membership a teammate
decided the task before the join in (docs/failover.md, "A robot that
starts again")."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Mapping, Sequence
from typing import NamedTuple

from ..transport.base import ClientTransport, Endpoint, PeerGone, TransportError
from ..transport.messages import ContentFormat, Method, Request
from .observed_states import STATE_PATH
from .robot_state import Decision, RobotState

log = logging.getLogger(__name__)

#: How soon a joining robot observes a silent teammate again.
JOIN_RETRY_S = 0.5


class Shown(NamedTuple):
    """The decision a teammate showed the joiner, which takes its membership."""

    teammate: str
    decision: Decision


async def decided_before(transport: ClientTransport, endpoints: Mapping[str, Endpoint], teammates: Sequence[str],
                         seq: int, patience: float, joiner: str) -> tuple[Shown | None, bool]:
    """The decision of task ``seq - 1`` the first of ``teammates`` to show
    one shows (with its membership), all of them observed at once (some may
    be down); None if none can show it.  A decision of task ``seq`` itself
    that counts ``joiner`` a member does as well: the teammate admitted it
    there and decided the task without a plan of it (a repeat skipped on
    its claim needs none), and waits for its plan for the next (found in
    the simulator: a joiner that took such a teammate for one past its join
    started a membership of its own, alone).  And whether one of them may
    have decided it unseen: it was already past the task (False: no process
    that decided it is left, each being a new one that decided nothing, or
    none listening).

    A teammate that stays silent is waited for, however long: silence is
    no sign that its process is gone (one cut off, or frozen, decided the
    task and decides on in the membership the joiner must take; a joiner
    that started a fresh one without it after a wait split the cluster in
    two memberships: simulator seed 1114 of nine robots with power cuts).
    Every fault the team is built for ends, and a process that died
    answers "nobody here".  Each observation that gets no answer within
    ``patience`` seconds is started again, so a teammate back from a
    partition is reached at the first retransmission after it, not at the
    end of a backoff grown through the partition; and the wait is logged
    once after that long."""
    request = Request(Method.GET, STATE_PATH, accept=ContentFormat.CBOR)

    async def shown_by(robot_id: str) -> Shown | bool:
        """Observe ``robot_id``'s state until it shows its decision of
        ``seq - 1``; False once it cannot (no process there, or a new one
        that decided nothing), True if it is past the task without
        ``joiner``."""
        while True:
            try:
                async with asyncio.timeout(patience) as first_answer:
                    async for response in transport.observe(endpoints[robot_id], request):
                        first_answer.reschedule(None)  # observing: its state changes when it decides
                        state = RobotState.decode(response.payload) if response.status.is_success else None
                        last = state.last if state is not None else None
                        if state is not None and last is None:
                            return False  # a process that never decided: restarted, not yet joined
                        if last is not None and last.seq >= seq - 1:
                            # Past seq - 1 only by a task that needs no plans
                            # (with the joiner a member), or having left it out.
                            taken = last.seq == seq - 1 or (last.seq == seq and joiner in last.members)
                            return Shown(robot_id, last) if taken else True
            except PeerGone as exc:
                log.debug("catching up from %s: %s", robot_id, exc)
                return False
            except (TransportError, ValueError, TimeoutError) as exc:
                log.debug("catching up from %s: %s", robot_id, exc or "no answer")
            await asyncio.sleep(JOIN_RETRY_S)  # silent, or the observation ended: again

    # Tasks made here and read in the teammates' order (a set of done tasks
    # iterates in an order that follows id()).
    watches = [asyncio.create_task(shown_by(r)) for r in teammates]
    past = False
    waited = False
    try:
        pending = set(watches)
        while pending:
            done, pending = await asyncio.wait(pending, timeout=None if waited else patience,
                                               return_when=asyncio.FIRST_COMPLETED)
            if not done and not waited:
                silent = [r for r, w in zip(teammates, watches, strict=True) if w in pending]
                log.warning("no teammate showed its decision of task %d within %gs; waiting on for %s",
                            seq - 1, patience, ", ".join(silent))
                waited = True
            for watch in watches:
                if watch in done:
                    found = watch.result()
                    if isinstance(found, tuple):
                        return found, past
                    past = past or found
    finally:
        for watch in watches:
            watch.cancel()
        await asyncio.gather(*watches, return_exceptions=True)
    return None, past
