"""A robot's view of its cluster: its own state, its teammates' planned
states (observed by :class:`~.observed_states.ObservedStates`, which also
finds a silent teammate down), and the calls that ask them.  Who is in, from
which task, in which epoch is the :class:`~.team_membership.TeamMembership`
it holds; counting again on a teammate wrongly found down, its
:class:`~.teammate_revival.TeammateRevival`."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Mapping, Sequence
from dataclasses import replace

from ..transport.base import ClientTransport, Endpoint, TransportError
from ..transport.messages import ContentFormat, Method, Request
from .local_health import LoopHealth
from .observed_states import PLAN_PATH, ObservedStates, States, indirect_probe, liveness_floor_s
from .robot_state import Decision, PlannedState, RobotState
from .task_assigner import robot_sort_key
from .team_membership import TeamMembership
from .teammate_revival import TeammateRevival

log = logging.getLogger(__name__)


class TeamView:
    """This robot's own state plus its teammates' planned states, the
    membership each task is decided in (:attr:`membership`), and the
    revival of teammates wrongly found down (:attr:`revival`).

    A teammate down without a plan after a task leaves the membership
    from the next (:meth:`planned_states`); a restarted robot joins at the
    task the feeder names (:meth:`join`)."""

    def __init__(
        self,
        own: RobotState,
        teammates: Mapping[str, Endpoint],
        transport: ClientTransport,
        link_kbps: float | None = None,
        health: LoopHealth | None = None,
    ) -> None:
        self._own = own
        self._teammates = ObservedStates(
            transport, teammates, PLAN_PATH, liveness=True, liveness_floor_s=liveness_floor_s(link_kbps),
            health=health,
        )
        self._peers = set(teammates)
        self._transport = transport
        self._endpoints = dict(teammates)
        self._teammates.confirm_silence = self._ask_others
        self.membership = TeamMembership(own.robot_id, teammates, transport, self._teammates)
        self.revival = TeammateRevival(teammates, transport, self._teammates, self.membership)

    @property
    def own(self) -> RobotState:
        return self._own

    def set_own(self, state: RobotState) -> None:
        self._own = state

    def start(self) -> None:
        self._teammates.start()

    async def heard_from(self, timeout: float) -> list[str]:
        """The teammates heard from once :meth:`ObservedStates.heard_from_all`
        returns (every one, or ``timeout`` passed)."""
        return await self._teammates.heard_from_all(timeout)

    @property
    def join_wait_s(self) -> float:
        """How long a starting robot waits to hear from its teammates: one
        liveness timeout (two floors before any sample: a teammate still
        starting, a lossy link's first exchanges); one that stays silent is
        the liveness probes' to find."""
        return self._teammates.liveness_timeout_s

    async def aclose(self) -> None:
        await self.revival.aclose()
        await self._teammates.aclose()

    async def _ask_others(self, robot_id: str) -> bool:
        """Whether another live teammate reaches ``robot_id`` now: up to
        :data:`INDIRECT_PROBES` of them probe it (``GET /robot/plan?probe=X``)."""
        others = [self._endpoints[r] for r in sorted(self._peers) if r != robot_id and self.is_up(r)]
        return await indirect_probe(self._transport, others, robot_id, self._teammates.request_timeout_s)

    async def reaches(self, robot_id: str) -> bool:
        """Whether this robot reaches teammate ``robot_id`` now (one request,
        for a teammate's indirect probe)."""
        if robot_id not in self._peers:
            return False
        try:
            response = await self._transport.request(
                self._endpoints[robot_id], Request(Method.GET, PLAN_PATH, accept=ContentFormat.CBOR),
                timeout=self._teammates.request_timeout_s,
            )
        except TransportError:
            return False
        return response.status.is_success

    def state_of(self, robot_id: str) -> RobotState | None:
        """The last state observed of teammate ``robot_id`` (served as ``?of=``)."""
        return self._teammates.states.get(robot_id)

    async def request_failed(self, robot_id: str, exc: Exception) -> None:
        """A query to teammate ``robot_id`` failed at the transport: a failure
        of a request like a liveness probe's (two in a row: down)."""
        await self._teammates.record_failure(robot_id, exc)

    @property
    def teammates(self) -> list[str]:
        """This robot's cluster but itself, in the team's order."""
        return sorted(self._peers, key=robot_sort_key)

    def in_cluster(self, robot_id: str) -> bool:
        """Whether ``robot_id`` is one of this robot's cluster (itself included)."""
        return robot_id == self._own.robot_id or robot_id in self._peers

    def saw_process(self, robot_id: str, boot: int) -> None:
        """Process ``boot`` of teammate ``robot_id`` sent its decision here, as the leader."""
        self._teammates.saw_process(robot_id, boot)

    def used_plans(self, decision: Decision) -> None:
        """``decision`` is carried out here: the teammates it was computed on
        (those it costs) had a plan right after the task before it."""
        for robot_id in decision.costs:
            if robot_id in self._peers:
                self._teammates.saw_plan(robot_id, decision.seq - 1)

    def is_up(self, robot_id: str) -> bool:
        """False once ``robot_id`` is known to be down (for the Query Handler)."""
        return robot_id not in self._teammates.down

    @property
    def down(self) -> Mapping[str, str]:
        """Teammates declared down, and why."""
        return self._teammates.down

    @property
    def request_timeout_s(self) -> float:
        """A liveness request's timeout: it follows the measured round trip."""
        return self._teammates.request_timeout_s

    def stalled_within(self, window_s: float) -> float:
        """How long this process's loop stood still at most, in a stall that
        ended in the last ``window_s`` seconds (0 when nothing measures it)."""
        health = self._teammates.health
        return health.stalled_within(window_s) if health is not None else 0.0

    async def probe(self, robot_id: str) -> None:
        """Ask teammate ``robot_id`` for its state now (two failures: down)."""
        if robot_id in self._peers and robot_id not in self._teammates.down:
            await self._teammates.probe(robot_id)

    async def until_down(self, robot_id: str) -> str:
        """Wait until teammate ``robot_id`` is declared down (the stalled wait
        asks it, as any wait does); returns why."""
        await self._teammates.wait(lambda _: robot_id in self._teammates.down, None)
        return self._teammates.down[robot_id]

    def forget_suspicions(self) -> None:
        """Count on every teammate again, as a new process does: this robot,
        left out, joins its teammates' membership again, and a teammate it
        has down there would be left out of it alone (each is found down
        again if it is)."""
        for robot_id in list(self._teammates.down):
            self._teammates.readmit(robot_id)

    async def join(self, seq: int, patience: float, joining: Sequence[str] = ()) -> bool:
        """This robot (restarted) joins at task ``seq``: it takes the
        membership the teammates decided task ``seq - 1`` in
        (:meth:`.TeamMembership.join`) and shows a plan right after
        ``seq - 1``, which the others wait for before deciding ``seq``.
        False if it found itself left out instead."""
        joined = await self.membership.join(seq, patience, joining)
        self._own = replace(self._own, plan=replace(self._own.plan, seq=seq - 1), prev=None, joined=joined.on)
        return joined.admits

    async def planned_states(self, seq: int, timeout: float) -> dict[str, PlannedState]:
        """Every member's planned state right after task ``seq``; waits for
        teammates that have not decided it yet, for at most ``timeout`` seconds
        or as long as finding a silent teammate down takes, if longer: a
        robot that gave up first would decide alone, without the dead
        teammate's last plan that the others hold (found in the simulator).
        A teammate that is down without a plan for ``seq`` leaves the team from
        task ``seq + 1`` on (:meth:`.TeamMembership.leave_out`)."""
        timeout = max(timeout, self._teammates.detection_s)
        down = self._teammates.down
        membership = self.membership
        expected = self._peers - set(membership.excluded)

        def missing(states: States) -> list[str]:
            return [r for r in expected
                    if not (r in down or membership.forgoes(r, seq) or (r in states and states[r].plan_at(seq) is not None))]

        try:
            # Due at once: this robot has its own plan after task seq, and its teammates decide alike.
            states = await self._teammates.wait(lambda s: not missing(s), timeout, pending=missing)
        except TimeoutError:
            states = self._teammates.states
            late = sorted(r for r in expected if r not in states or states[r].plan_at(seq) is None)
            raise TransportError(f"no state for task {seq} from {', '.join(late)} within {timeout:g}s") from None
        own = self._own.plan_at(seq)
        if own is None:
            raise TransportError(f"own state for task {seq} is gone")
        plans = {r: states[r].plan_at(seq) for r in expected if r in states and not membership.forgoes(r, seq)}
        for robot_id in sorted(expected):
            if plans.get(robot_id) is None and not membership.forgoes(robot_id, seq):
                plans[robot_id] = await self._plan_from_survivors(robot_id, seq)
            if plans.get(robot_id) is None and robot_id not in self._teammates.gone and membership.outnumbered:
                # Down for its silence, with no majority up: this robot may
                # be the one cut off, and the others, counting it, decide on
                # with the teammate it has down.  Leaving that one out would
                # be a membership of its own, in an epoch ahead of theirs,
                # and the feeder voids the decisions of robots left out of a
                # newer membership: the majority's.  It settles the task
                # instead, asking the ones it has down too (found in the
                # simulator: a robot cut off for 21 s, whose observation of
                # a teammate never started, left it out once the partition
                # healed).  A teammate whose process is known gone is no
                # sign of that, and leaves as before.
                raise TransportError(f"{robot_id} is down without a plan after task {seq}, and this robot has "
                                     "no majority of its cluster up: it leaves nobody out")
            if plans.get(robot_id) is None:
                why = down.get(robot_id, f"a teammate had no plan of it after task {seq}")
                membership.leave_out(robot_id, seq, why)
        plans[self._own.robot_id] = own
        return {r: p for r, p in plans.items() if p is not None}

    async def _plan_from_survivors(self, robot_id: str, seq: int) -> PlannedState | None:
        """``robot_id`` (down) after task ``seq`` as some survivor saw it.  The
        last plan a robot published before dying may have reached one teammate
        and not another; asking keeps "compute by all" on the same inputs:
        a survivor that has it includes the dead robot, and so do the others."""
        excluded = self.membership.excluded
        survivors = sorted(r for r in self._peers if r not in self._teammates.down and r not in excluded)
        heard = await asyncio.gather(*(self._teammates.hearsay(r, robot_id, seq, self._own.robot_id) for r in survivors))
        for state in heard:
            plan = state.plan_at(seq) if state is not None else None
            if plan is not None:
                log.info("%s's plan after task %d came from a teammate", robot_id, seq)
                return plan
        return None
