"""The fence for a robot that was only cut off: it picks only
while it holds a lease from a majority of its cluster.

A robot that was stopped or cut off is declared down by the others, which
give its unexecuted tasks to survivors; when it comes back its Task
Executor still holds those jobs.  :class:`Lease` keeps the two from
overlapping: before each pick, and again when the pick is over, the robot
needs grants from a majority of its cluster (itself counted) to a round of
``GET /robot/lease?r=ME&t=TASK`` sent at ``t``, valid until ``t + lease_s``
on its own monotonic clock and for jobs of tasks up to ``TASK``.  A
teammate grants only a robot it counts as an up member, and only once it
has decided ``TASK`` with that robot a member (5.03 until it has decided
it); a robot no majority will grant drops its jobs unexecuted and says so
in its live state (``fenced``).

docs/failover.md ("The fence") specifies the holder, the granter, when the
feeder may re-feed a down robot's tasks, and why a robot whose teammates
are all down picks nothing.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable, Mapping

from .. import clock
from ..cancelling import cancel_and_wait
from ..transport.base import ClientTransport, Endpoint, TransportError
from ..transport.messages import Method, Request, Status

log = logging.getLogger(__name__)

LEASE_PATH = "/robot/lease"


def lease_duration_s(liveness_floor_s: float) -> float:
    """A lease three liveness floors long (3 s on loopback, 15 s on a slow
    radio link): several renewals' round trips fit, and the feeder's wait
    before re-assigning stays within a few failure-detection times."""
    return 3 * liveness_floor_s


class Lease:
    """This robot's lease, renewed on demand from its ``teammates``
    (the cluster's other robots, by id)."""

    def __init__(
        self,
        robot_id: str,
        teammates: Mapping[str, Endpoint],
        transport: ClientTransport,
        duration_s: float,
        *,
        request_timeout_s: Callable[[], float],
        down: Callable[[], Mapping[str, str]],
        left_out: Callable[[], Mapping[str, int]] = dict,
        on_failure: Callable[[str, Exception], Awaitable[None]] | None = None,
    ) -> None:
        self.robot_id = robot_id
        self._teammates = dict(teammates)
        self._transport = transport
        self.duration_s = duration_s
        self._request_timeout_s = request_timeout_s
        self._down = down
        #: Teammate -> the first task this robot left it out of.
        self._left_out = left_out
        self._on_failure = on_failure
        #: Grants needed from teammates: with this robot, a majority of the cluster.
        self.needed = (len(self._teammates) + 1) // 2
        self._until = float("-inf")
        #: The latest task the lease was granted for (0: none named).
        self._task = 0
        self.renewals = 0

    @property
    def valid_until(self) -> float:
        return self._until

    async def hold(self, for_s: float, task: int = 0) -> str | None:
        """None once the lease covers the next ``for_s`` seconds (renewed if
        needed; waits while no majority answers either way); else why this
        robot is fenced.  ``task``: the task whose job it is for; a lease
        granted for an earlier one is asked again, of teammates that grant
        it only once they decided that task with this robot a member (one
        they had left out, still granted from before, picked the task they
        gave another: simulator, section 4 of docs/simulation.md)."""
        for_s = min(for_s, self.duration_s / 2)
        backoff = 0.2
        while clock.monotonic() + for_s >= self._until or task > self._task:
            if self.needed == 0:
                return None  # a cluster of one: nobody else could take its tasks
            sent = clock.monotonic()
            refused = await self._round(task)
            if refused is None:
                self._until = sent + self.duration_s
                self._task = max(self._task, task)
                self.renewals += 1
                continue
            if refused:
                return refused
            # Neither a majority nor a refusal: cut off, or the others are
            # slow.  Ask again shortly (never pick meanwhile).
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2, 2.0)
        return None

    async def _round(self, task: int) -> str | None:
        """One renewal round (for ``task``, if not 0): None if granted; a
        reason if a majority can no longer grant; "" if undecided.  Only as
        many teammates as a majority needs are asked first; the next when
        one does not grant, and all the rest once half a request timeout
        passes without an answer.  A round a task asks twice as many
        teammates as needed otherwise, in a 3-robot cluster, for nothing."""
        down = self._down()
        verdicts: dict[str, str] = {r: f"down ({why})" for r, why in down.items() if r in self._teammates}
        # A teammate this robot left out before the task decides it in no
        # membership of this robot's: it may never decide it at all (not fed),
        # and its "not yet" held the job for good (simulator, nine robots with
        # partitions, seed 9188: the cluster never finished).
        verdicts |= {r: f"left out of this robot's membership from task {first}"
                     for r, first in self._left_out().items()
                     if r in self._teammates and r not in verdicts and task and first <= task}
        waiting = [r for r in self._teammates if r not in verdicts]
        timeout = self._request_timeout_s()
        request = Request(Method.GET, LEASE_PATH, {"r": self.robot_id, **({"t": str(task)} if task else {})})
        pending: dict[asyncio.Future[tuple[str, str | None]], str] = {}

        def ask_next() -> None:
            mate = waiting.pop(0)
            pending[asyncio.ensure_future(self._ask(mate, request, timeout))] = mate

        for _ in range(min(self.needed, len(waiting))):
            ask_next()
        granted = 0
        try:
            while pending:
                done, _ = await asyncio.wait(pending, timeout=timeout / 2 if waiting else None,
                                             return_when=asyncio.FIRST_COMPLETED)
                if not done:  # slow: the rest too
                    while waiting:
                        ask_next()
                    continue
                for answered in [f for f in pending if f in done]:  # in the order asked, not id()'s
                    robot_id, verdict = answered.result()
                    del pending[answered]
                    if verdict is None:
                        granted += 1
                        if granted >= self.needed:
                            return None
                    else:
                        verdicts[robot_id] = verdict
                        if waiting:
                            ask_next()
        finally:
            await cancel_and_wait(pending)
        refusals = {r: v for r, v in verdicts.items() if not v.startswith("no answer")}
        if len(self._teammates) - len(refusals) < self.needed:
            return "no lease from a majority of the cluster (" + "; ".join(
                f"{r}: {v}" for r, v in sorted(verdicts.items())) + ")"
        return ""

    async def _ask(self, robot_id: str, request: Request, timeout: float) -> tuple[str, str | None]:
        try:
            response = await self._transport.request(self._teammates[robot_id], request, timeout=timeout)
        except TransportError as exc:
            if self._on_failure is not None:
                await self._on_failure(robot_id, exc)  # counts towards failure detection
            return robot_id, f"no answer: {exc}"
        if response.status.is_success:
            return robot_id, None
        if response.status == Status.FORBIDDEN:
            return robot_id, f"refused: {response.text()}"
        return robot_id, f"no answer: {response.status.dotted} {response.text()}"
