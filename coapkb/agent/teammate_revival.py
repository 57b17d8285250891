"""A teammate this robot declared down, counted on again when it shows it is
alive while this robot has no majority up: the suspicion was this robot's
own, for it was the one cut off, and the others went on counting it
(docs/failover.md)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Mapping

from ..cancelling import cancel_and_wait
from ..transport.base import ClientTransport, Endpoint, TransportError
from ..transport.messages import ContentFormat, Method, Request
from .lease import LEASE_PATH
from .observed_states import STATE_PATH, ObservedStates
from .robot_state import RobotState
from .team_membership import Membership, TeamMembership

log = logging.getLogger(__name__)


class TeammateRevival:
    """Counting on a teammate again after a false suspicion: the same
    process (the ``boot`` last seen) is asked once for its state, and is
    up again if it answers.  It is never granted a lease again
    (:attr:`.TeamMembership.refused`)."""

    def __init__(self, teammates: Mapping[str, Endpoint], transport: ClientTransport, observed: ObservedStates,
                 membership: TeamMembership) -> None:
        self._peers = set(teammates)
        self._endpoints = dict(teammates)
        self._transport = transport
        self._teammates = observed
        self._membership = membership
        self._reviving: dict[str, asyncio.Future[bool]] = {}
        self._background: set[asyncio.Task[bool]] = set()

    async def aclose(self) -> None:
        await cancel_and_wait(self._background)

    async def heard_again(self, robot_id: str) -> bool:
        """Teammate ``robot_id``, a member this robot has down, showed it is
        alive (it answered, or asked for a lease) while this robot is
        :attr:`~.TeamMembership.alone`: the suspicion was this robot's own
        (it was the one cut off, and the others went on, counting it).
        Asked once for its state, the same process (the ``boot`` last seen)
        is counted on again: this robot waits for its plans, asks it,
        decides with it.  It is never granted a lease again (refused): it
        was refused once, and the feeder may have re-assigned its tasks on
        that refusal.  Whether it is up now."""
        if robot_id not in self._peers:
            return False
        if robot_id not in self._teammates.down:
            return True
        known = self._teammates.states.get(robot_id)
        if self._membership.left_out(robot_id) or not self._membership.alone or known is None or not known.boot:
            return False
        pending = self._reviving.get(robot_id) or self._start(robot_id, known.boot)
        try:
            return await asyncio.shield(pending)
        except Exception:  # noqa: BLE001 - a probe that failed revives nothing
            return False

    def led_by(self, leader: str, boot: int, membership: Membership) -> bool:
        """Teammate ``leader``, which this robot has down, sent the decision
        it computed as the leader of ``membership`` ("compute and
        communicate"): if that is this robot's membership now (its epoch,
        this robot and the leader members, nobody left out here), the
        suspicion is stale however many teammates are up, and it is counted
        on again as :meth:`heard_again` counts one (the same process, that
        counts this robot), in the background.  A follower that kept its
        leader down after the leader's cut healed decided the next task
        alone, leaving out the leader its joined teammate followed
        (simulator, six robots, seed 21881: no task came while the link was
        back and this robot alone).  Whether it asks the leader."""
        mine = self._membership
        if (leader not in self._peers or leader not in self._teammates.down or mine.left_out(leader)
                or membership.epoch != mine.epoch or {leader, mine.robot_id} - set(membership.members)):
            return False
        known = self._teammates.states.get(leader)
        if known is None or known.boot != boot or leader in self._reviving:
            return False
        task = self._start(leader, boot)
        self._background.add(task)
        task.add_done_callback(self._background.discard)
        return True

    def _start(self, robot_id: str, boot: int) -> asyncio.Task[bool]:
        """Ask ``robot_id`` (process ``boot``) once whether it is back; one such question at a time."""
        pending = self._reviving[robot_id] = asyncio.create_task(self._revive(robot_id, boot))
        pending.add_done_callback(lambda _: self._reviving.pop(robot_id, None))
        return pending

    def asked_by(self, robot_id: str) -> None:
        """Teammate ``robot_id`` asked this robot for something (a lease):
        if this robot has it down and is alone, see whether it is back
        (:meth:`heard_again`), without holding the answer up."""
        if robot_id in self._peers and robot_id in self._teammates.down and self._membership.alone:
            task = asyncio.create_task(self.heard_again(robot_id), name=f"revive {robot_id}")
            self._background.add(task)
            task.add_done_callback(self._background.discard)

    def _went_on_without(self, state: RobotState) -> bool:
        """Whether ``state``'s last decision left this robot out: then the
        suspicion was not this robot's alone.  Counted on again, the teammate
        was a member of this robot's membership but not this robot of its
        own, and the two left the third out in two memberships of one epoch
        (simulator, nine robots, seed 4496: a robot cut off for 20 s)."""
        last = state.last
        if last is None or not last.epoch or self._membership.robot_id in last.members:
            return False
        log.info("%s answers, but decided task %d without this robot (epoch %d): not counted on again",
                 state.robot_id, last.seq, last.epoch)
        return True

    async def _counts_this_robot(self, robot_id: str) -> bool:
        """Whether teammate ``robot_id`` counts this robot as up and a member
        (``GET /robot/lease?r=ME&counts``).  One that has this robot down,
        not alone, leaves it out at its next task: counted on again, it was a
        member of this robot's membership while this robot was none of its
        own, and the two left the third out in two memberships of one epoch
        (simulator, nine robots with partitions, seed 2716: a robot cut off
        for 3.5 s counted again on a teammate that had it down, and a third
        robot frozen)."""
        me = self._membership.robot_id
        try:
            response = await self._transport.request(
                self._endpoints[robot_id], Request(Method.GET, LEASE_PATH, {"r": me, "counts": ""}),
                timeout=self._teammates.request_timeout_s,
            )
        except TransportError as exc:
            log.debug("asking %s whether it counts %s: %s", robot_id, me, exc)
            return False
        if not response.status.is_success:
            log.info("%s answers, but does not count this robot (%s): not counted on again", robot_id,
                     response.text())
        return response.status.is_success

    async def _revive(self, robot_id: str, boot: int) -> bool:
        try:
            # The whole state: its last decision says whom it decides with.
            response = await self._transport.request(
                self._endpoints[robot_id], Request(Method.GET, STATE_PATH, accept=ContentFormat.CBOR),
                timeout=self._teammates.request_timeout_s,
            )
            state = RobotState.decode(response.payload) if response.status.is_success else None
        except (TransportError, ValueError) as exc:
            log.debug("asking %s again: %s", robot_id, exc)
            return False
        if state is None or state.boot != boot:
            return False  # another process: it joins at a task boundary
        if self._went_on_without(state) or not await self._counts_this_robot(robot_id):
            return False
        if robot_id in self._teammates.down and not self._membership.left_out(robot_id):
            self._membership.refused.add(robot_id)
            await self._teammates.revive(robot_id)
        return robot_id not in self._teammates.down
