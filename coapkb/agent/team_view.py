"""A robot's view of its cluster: its own state, its teammates' planned
states (observed by :class:`~.observed_states.ObservedStates`, which also
finds a silent teammate down), and the membership each task is decided in:
who is in, from which task, in which epoch."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

from ..transport.base import ClientTransport, Endpoint, TransportError
from ..transport.messages import ContentFormat, Method, Request
from .joining import decided_before
from .local_health import LoopHealth
from .observed_states import PLAN_PATH, ObservedStates, States, indirect_probe, liveness_floor_s
from .robot_state import PlannedState, RobotState

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class Membership:
    """Who takes part in assigning a task.  ``epoch`` counts the membership
    changes so far; every decision names it, so the record shows that the
    survivors decided with the same team."""

    epoch: int
    members: tuple[str, ...]


class TeamView:
    """This robot's own state plus its teammates' planned states.

    Membership: a teammate declared down (failed liveness requests) is
    excluded from task ``k`` on, where ``k`` is the first task it did not
    publish a plan for; every survivor that saw the same plans derives the
    same ``k``.  A restarted robot is admitted again at the task the feeder
    names in that task's post (the task stream orders joins for everyone);
    the joiner copies the membership the others decided the previous task in
    (:meth:`join`).  Each change, out or in, is one epoch."""

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
        #: Teammate -> the first task it is excluded from.
        self.excluded: dict[str, int] = {}
        #: Membership changes so far (exclusions and admissions).
        self.epoch = 0
        #: Teammate -> the task after which this robot told another it had no
        #: plan of it: a plan arriving later is not used, so both decide alike.
        self._forgone: dict[str, int] = {}
        #: Teammates this robot declared down and counts on again (:meth:`heard_again`):
        #: their processes are never granted a lease again (the fence).
        self.refused: set[str] = set()
        self._reviving: dict[str, asyncio.Future[bool]] = {}
        self._background: set[asyncio.Task[bool]] = set()

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
        for task in self._background:
            task.cancel()
        await asyncio.gather(*self._background, return_exceptions=True)
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

    def in_cluster(self, robot_id: str) -> bool:
        """Whether ``robot_id`` is one of this robot's cluster (itself included)."""
        return robot_id == self._own.robot_id or robot_id in self._peers

    async def forgo(self, robot_id: str, seq: int) -> None:
        """Another robot asked for ``robot_id``'s plan after task ``seq`` and
        this one had none: it will not use one arriving late either (the
        asker excludes ``robot_id``, and so must this robot)."""
        if robot_id in self._peers and seq < self._forgone.get(robot_id, seq + 1):
            self._forgone[robot_id] = seq
            await self._teammates.poke()

    def saw_process(self, robot_id: str, boot: int) -> None:
        """Process ``boot`` of teammate ``robot_id`` sent its decision here, as the leader."""
        self._teammates.saw_process(robot_id, boot)

    def _forgoes(self, robot_id: str, seq: int) -> bool:
        return self._forgone.get(robot_id, seq + 1) <= seq

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

    def grant(self, robot_id: str) -> str | None:
        """None if this robot grants teammate ``robot_id`` a lease (it counts
        it as up and a member), else why not.  Once refused, a process is
        never granted again: the others may be re-assigning its tasks
        (:mod:`coapkb.agent.lease`)."""
        if robot_id not in self._peers:
            return f"{robot_id} is not in this robot's cluster"
        if robot_id in self._teammates.down:
            return f"{self._own.robot_id} has {robot_id} down: {self._teammates.down[robot_id]}"
        if robot_id in self.excluded or robot_id in self._forgone:
            return f"{self._own.robot_id} has left {robot_id} out of the membership"
        if robot_id in self.refused:
            return f"{self._own.robot_id} had {robot_id} down: it never grants that process again"
        return None

    @property
    def alone(self) -> bool:
        """Whether the members this robot counts as up, itself counted, are
        no majority of the cluster, while it has left nobody out: then it
        may be the one cut off, and decides nothing alone against teammates
        that may still count it (:meth:`heard_again`).  A robot that left a
        teammate out has a membership of its own (another epoch): counting
        on the others again would not make it decide as they do (found in
        the simulator), and it stays as it is."""
        return not self.excluded and self._outnumbered

    @property
    def _outnumbered(self) -> bool:
        """Whether the members this robot counts as up, itself counted, are
        no majority of the cluster."""
        up = sum(1 for r in self.membership.members if r == self._own.robot_id or self.is_up(r))
        return up <= (len(self._peers) + 1) // 2

    async def heard_again(self, robot_id: str) -> bool:
        """Teammate ``robot_id``, a member this robot has down, showed it is
        alive (it answered, or asked for a lease) while this robot is
        :attr:`alone`: the suspicion was this robot's own (it was the one cut
        off, and the others went on, counting it).  Asked once for its state,
        the same process (the ``boot`` last seen) is counted on again: this
        robot waits for its plans, asks it, decides with it.  It is never
        granted a lease again (:attr:`refused`): it was refused once, and the
        feeder may have re-assigned its tasks on that refusal.  Whether it is
        up now."""
        if robot_id not in self._peers:
            return False
        if robot_id not in self._teammates.down:
            return True
        known = self._teammates.states.get(robot_id)
        if (robot_id in self.excluded or robot_id in self._forgone or not self.alone
                or known is None or not known.boot):
            return False
        pending = self._reviving.get(robot_id)
        if pending is None:
            pending = self._reviving[robot_id] = asyncio.ensure_future(self._revive(robot_id, known.boot))
            pending.add_done_callback(lambda _: self._reviving.pop(robot_id, None))
        try:
            return await asyncio.shield(pending)
        except Exception:  # noqa: BLE001 - a probe that failed revives nothing
            return False

    def asked_by(self, robot_id: str) -> None:
        """Teammate ``robot_id`` asked this robot for something (a lease):
        if this robot has it down and is :attr:`alone`, see whether it is
        back (:meth:`heard_again`), without holding the answer up."""
        if robot_id in self._peers and robot_id in self._teammates.down and self.alone:
            task = asyncio.create_task(self.heard_again(robot_id), name=f"revive {robot_id}")
            self._background.add(task)
            task.add_done_callback(self._background.discard)

    async def _revive(self, robot_id: str, boot: int) -> bool:
        try:
            response = await self._transport.request(
                self._endpoints[robot_id], Request(Method.GET, PLAN_PATH, accept=ContentFormat.CBOR),
                timeout=self._teammates.request_timeout_s,
            )
            state = RobotState.decode(response.payload) if response.status.is_success else None
        except (TransportError, ValueError) as exc:
            log.debug("asking %s again: %s", robot_id, exc)
            return False
        if state is None or state.boot != boot:
            return False  # another process: it joins at a task boundary
        if robot_id in self._teammates.down and robot_id not in self.excluded and robot_id not in self._forgone:
            self.refused.add(robot_id)
            await self._teammates.revive(robot_id)
        return self.is_up(robot_id)

    async def probe(self, robot_id: str) -> None:
        """Ask teammate ``robot_id`` for its state now (two failures: down)."""
        if robot_id in self._peers and robot_id not in self._teammates.down:
            await self._teammates.probe(robot_id)

    async def until_down(self, robot_id: str) -> str:
        """Wait until teammate ``robot_id`` is declared down (the stalled wait
        asks it, as any wait does); returns why."""
        await self._teammates.wait(lambda _: robot_id in self._teammates.down, None)
        return self._teammates.down[robot_id]

    @property
    def membership(self) -> Membership:
        members = (self._peers - set(self.excluded)) | {self._own.robot_id}
        return Membership(self.epoch, tuple(sorted(members)))

    def admit(self, robot_id: str) -> None:
        """Teammate ``robot_id`` (restarted) is a member again from the task
        being decided now; its new process's plans are awaited like anyone's.
        A new epoch if it had been left out; one restarted before the
        membership left it out is a member still, in the same epoch.  Each
        robot of the cluster reads that from the membership of the task
        before, the joiners too (:meth:`_joined`), so a join list that named
        a robot to some and not to others (the feeder names to the teammates
        only the joiners its post reached) cannot set their epochs apart
        (found in the simulator: a robot killed again before it took its
        join, named to its co-joiner only, which then named an epoch one
        ahead of its teammate's on every task)."""
        if robot_id not in self._peers:
            return
        log.warning("%s joins the team again", robot_id)
        if self.excluded.pop(robot_id, None) is not None:
            self.epoch += 1
        self._forgone.pop(robot_id, None)  # a promise about its old process
        self.refused.discard(robot_id)  # and a refusal of it
        self._teammates.readmit(robot_id)

    def adopt(self, membership: Membership, seq: int) -> None:
        """Take the membership the leader decided task ``seq`` in, if newer
        than this robot's own ("compute and communicate": a follower does not
        compute who is down, and must not name an older epoch than the
        decision it carries out; found in the simulator)."""
        if membership.epoch <= self.epoch or not membership.members:
            return
        members = set(membership.members)
        for robot_id in self._peers - members:
            self.excluded.setdefault(robot_id, seq)
        for robot_id in members & set(self.excluded):
            del self.excluded[robot_id]
        self.epoch = membership.epoch

    async def join(self, seq: int, timeout: float, joining: Sequence[str] = ()) -> None:
        """This robot (restarted) joins at task ``seq``: it takes the
        membership the teammates decided task ``seq - 1`` in (a new epoch, its
        admission, if that membership had left it out) and shows a plan right after ``seq - 1``, which the others
        wait for before deciding ``seq``.

        ``joining``: every robot joining at ``seq`` (this one too).  When no
        teammate can show that decision -- each is joining too, or no process
        listens at its address, or it is a new process that has decided
        nothing yet -- no process that decided ``seq - 1`` survives (every
        robot restarted in turn, each before the previous one had joined), and
        the joiners start a fresh membership from the join list: its members
        are the joiners, its epoch the task's number, the same on each of them
        (found in the simulator: three robots restarted in turn logged
        "cannot join" and decided nothing).  The same when no teammate showed
        it within ``timeout``: the teammates the feeder counts decided
        ``seq - 1`` before it posted ``seq``, so one still silent is out."""
        if seq <= 1:
            # Nothing decided before: the membership is the cluster's first.
            self._joined(seq, Membership(0, ()))
            return
        co_joiners = {r for r in joining if r in self._peers}
        shown, unknown = await decided_before(self._transport, self._endpoints, sorted(self._peers - co_joiners),
                                              seq, timeout)
        membership = None if shown is None else Membership(*shown)
        if membership is None:
            log.warning("no teammate showed its decision of task %d%s: a fresh membership of the robots joining "
                        "at task %d", seq - 1, f" within {timeout:g}s" if unknown else " (none survives)", seq)
            membership = Membership(seq, tuple(sorted(co_joiners | {self._own.robot_id})))
        self._joined(seq, membership)

    def _joined(self, seq: int, membership: Membership) -> None:
        """Join at task ``seq`` on top of ``membership`` (see :meth:`join`)."""
        if membership.members:
            gone = self._peers - set(membership.members)
            self.excluded = {r: seq - 1 for r in gone}
        # Its admission is an epoch if that membership had left it out (see
        # :meth:`admit`); before any decision, nobody had.
        self.epoch = membership.epoch + (self._own.robot_id not in (membership.members or (self._own.robot_id,)))
        self._own = replace(self._own, plan=replace(self._own.plan, seq=seq - 1), prev=None)
        log.warning("joined the team at task %d (epoch %d, members %s)", seq, self.epoch,
                    ", ".join(self.membership.members))

    async def planned_states(self, seq: int, timeout: float) -> dict[str, PlannedState]:
        """Every member's planned state right after task ``seq``; waits for
        teammates that have not decided it yet, for at most ``timeout`` seconds
        or as long as finding a silent teammate down takes, if longer: a
        robot that gave up first would decide alone, without the dead
        teammate's last plan that the others hold (found in the simulator).
        A teammate that is down without a plan for ``seq`` leaves the team from
        task ``seq + 1`` on (see :attr:`membership`)."""
        timeout = max(timeout, self._teammates.detection_s)
        down = self._teammates.down
        expected = self._peers - set(self.excluded)

        def missing(states: States) -> list[str]:
            return [r for r in expected
                    if not (r in down or self._forgoes(r, seq) or (r in states and states[r].plan_at(seq) is not None))]

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
        plans = {r: states[r].plan_at(seq) for r in expected if r in states and not self._forgoes(r, seq)}
        for robot_id in sorted(expected):
            if plans.get(robot_id) is None and not self._forgoes(robot_id, seq):
                plans[robot_id] = await self._plan_from_survivors(robot_id, seq)
            if plans.get(robot_id) is None and robot_id not in self._teammates.gone and self._outnumbered:
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
                log.warning("%s is down (%s): excluded from task %d on", robot_id, why, seq + 1)
                self.excluded[robot_id] = seq + 1
                self.epoch += 1
        plans[self._own.robot_id] = own
        return {r: p for r, p in plans.items() if p is not None}

    async def _plan_from_survivors(self, robot_id: str, seq: int) -> PlannedState | None:
        """``robot_id`` (down) after task ``seq`` as some survivor saw it.  The
        last plan a robot published before dying may have reached one teammate
        and not another; asking keeps "compute by all" on the same inputs:
        a survivor that has it includes the dead robot, and so do the others."""
        survivors = sorted(r for r in self._peers if r not in self._teammates.down and r not in self.excluded)
        heard = await asyncio.gather(*(self._teammates.hearsay(r, robot_id, seq) for r in survivors))
        for state in heard:
            plan = state.plan_at(seq) if state is not None else None
            if plan is not None:
                log.info("%s's plan after task %d came from a teammate", robot_id, seq)
                return plan
        return None
