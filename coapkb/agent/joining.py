"""Where a restarted robot joins its cluster: the membership a teammate
decided the task before the join in (docs/failover.md, "A robot that
starts again")."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Mapping, Sequence

from ..transport.base import ClientTransport, Endpoint, PeerGone, TransportError
from ..transport.messages import ContentFormat, Method, Request
from .observed_states import STATE_PATH
from .robot_state import RobotState

log = logging.getLogger(__name__)

#: How soon a joining robot observes a silent teammate again.
JOIN_RETRY_S = 0.5

#: A membership as a decision names it: its epoch and its members.
Shown = tuple[int, tuple[str, ...]]


async def decided_before(transport: ClientTransport, endpoints: Mapping[str, Endpoint], teammates: Sequence[str],
                         seq: int, timeout: float) -> tuple[Shown | None, bool]:
    """The membership the first of ``teammates`` to show its decision of
    task ``seq - 1`` decided it in, all of them observed at once (some may
    be down), within ``timeout`` seconds; None if none showed it.  And
    whether one of them may have decided it unseen: it was past the task,
    or silent until the timeout (False: no process that decided it is
    left, each being a new one that decided nothing, or none listening)."""
    request = Request(Method.GET, STATE_PATH, accept=ContentFormat.CBOR)

    async def shown_by(robot_id: str) -> Shown | bool:
        """Observe ``robot_id``'s state until it shows its decision of
        ``seq - 1``; False once it cannot (no process there, or a new one
        that decided nothing), True if it is not known."""
        while True:
            try:
                async for response in transport.observe(endpoints[robot_id], request):
                    state = RobotState.decode(response.payload) if response.status.is_success else None
                    last = state.last if state is not None else None
                    if state is not None and last is None:
                        return False  # a process that never decided: restarted, not yet joined
                    if last is not None and last.seq >= seq - 1:
                        # None decides seq before this robot's plan for it is
                        # out, so seq - 1 is as far as a teammate can be.
                        return (last.epoch, last.members) if last.seq == seq - 1 else True
            except PeerGone as exc:
                log.debug("catching up from %s: %s", robot_id, exc)
                return False
            except (TransportError, ValueError) as exc:
                log.debug("catching up from %s: %s", robot_id, exc)
            await asyncio.sleep(JOIN_RETRY_S)  # silent, or the observation ended: until the timeout

    # Tasks made here, in the teammates' order (as_completed would start
    # bare coroutines in an order that follows id()).
    watches = [asyncio.create_task(shown_by(r)) for r in teammates]
    unknown = False
    try:
        async with asyncio.timeout(timeout):
            for first in asyncio.as_completed(watches):
                found = await first
                if isinstance(found, tuple):
                    return found, unknown
                unknown = unknown or found
    except TimeoutError:
        unknown = True
    finally:
        for watch in watches:
            watch.cancel()
        await asyncio.gather(*watches, return_exceptions=True)
    return None, unknown
