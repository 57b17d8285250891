"""Who takes part in deciding each task on a robot's cluster: who is left
out from which task, who is admitted again, and the epoch these changes
count (docs/failover.md).  Kept by :class:`TeamMembership`, which a robot's
:class:`~.team_view.TeamView` holds as its ``membership``."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from ..transport.base import ClientTransport, Endpoint
from .joining import plans_shown, shown_to_join
from .observed_states import ObservedStates
from .robot_state import NO_PROCESS, Decision

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Admission:
    """An admission that let ``robot_id`` in again at task ``seq``: the task
    it had been excluded from, and the epoch the admission made."""

    robot_id: str
    seq: int
    excluded_from: int
    epoch: int


@dataclass(frozen=True)
class Membership:
    """Who takes part in assigning a task.  ``epoch`` counts the membership
    changes so far; every decision names it, so the record shows that the
    survivors decided with the same team."""

    epoch: int
    members: tuple[str, ...]


@dataclass(frozen=True)
class Joined:
    """How a restarted robot joined: whether it admits its co-joiners (not
    when its teammates had left it out), and the teammate's decision whose
    membership it took, which its state shows until it decides a task."""

    admits: bool
    on: Decision | None


class TeamMembership:
    """The membership one robot decides its cluster's tasks in.

    A teammate declared down (failed liveness requests) is excluded from
    task ``k`` on, where ``k`` is the first task it did not publish a plan
    for (:meth:`leave_out`); every survivor that saw the same plans derives
    the same ``k``.  A restarted robot is admitted again at the task the
    feeder names in that task's post (the task stream orders joins for
    everyone); the joiner copies the membership the others decided the
    previous task in (:meth:`join`).  Each change, out or in, is one epoch.
    Which teammates are down is ``teammates``'s to find."""

    def __init__(self, robot_id: str, teammates: Mapping[str, Endpoint], transport: ClientTransport,
                 observed: ObservedStates) -> None:
        self.robot_id = robot_id
        self._peers = set(teammates)
        self._endpoints = dict(teammates)
        self._transport = transport
        self._teammates = observed
        #: Teammate -> the first task it is excluded from.
        self.excluded: dict[str, int] = {}
        #: Membership changes so far (exclusions and admissions).
        self.epoch = 0
        #: Teammate -> the task after which this robot told another it had no
        #: plan of it: a plan arriving later is not used, so both decide alike.
        self._forgone: dict[str, int] = {}
        #: Teammates this robot declared down and counts on again
        #: (:class:`~.teammate_revival.TeammateRevival`): their processes are
        #: never granted a lease again (the fence).
        self.refused: set[str] = set()
        #: Teammate -> the task it was last admitted at.
        self._admitted_at: dict[str, int] = {}
        #: (teammate, task) -> the process the feeder named for a join this
        #: robot has not admitted yet (:meth:`named`).
        self._named: dict[tuple[str, int], int] = {}
        #: The last admission that let a teammate in again (:meth:`missed` may undo it).
        self._last_admission: _Admission | None = None

    @property
    def members(self) -> tuple[str, ...]:
        """The members now, this robot included, sorted."""
        return self.current.members

    @property
    def current(self) -> Membership:
        """The membership now, as a decision names it."""
        members = (self._peers - set(self.excluded)) | {self.robot_id}
        return Membership(self.epoch, tuple(sorted(members)))

    def left_out(self, robot_id: str) -> bool:
        """Whether this robot left teammate ``robot_id`` out: excluded, or
        promised another robot not to use a plan of it (:meth:`forgo`)."""
        return robot_id in self.excluded or robot_id in self._forgone

    def heeds(self, asker: str | None) -> bool:
        """Whether a teammate's question binds this robot (:meth:`forgo`):
        it asks as a member (an unnamed asker is taken for one)."""
        return asker is None or not self.left_out(asker)

    async def forgo(self, robot_id: str, seq: int) -> None:
        """Another robot asked for ``robot_id``'s plan after task ``seq`` and
        this one had none: it will not use one arriving late either (the
        asker excludes ``robot_id``, and so must this robot).  A question
        about a task before ``robot_id`` was last admitted, the plan of a
        process that left, binds nothing: a try of it held back on the way
        and answered after the admission had left the new process out of
        the tasks after it, alone (found in the simulator, seed 686 of three
        robots with messages held back)."""
        if self._before_admission(robot_id, seq + 1):
            return
        if robot_id in self._peers and seq < self._forgone.get(robot_id, seq + 1):
            self._forgone[robot_id] = seq
            await self._teammates.poke()

    def _before_admission(self, robot_id: str, seq: int) -> bool:
        """Whether task ``seq`` comes before ``robot_id`` was last admitted:
        news of it (a plan for it, a restart during it) is about a process
        that left, held back on the way (the plan for task ``seq`` is the one
        right after ``seq - 1``)."""
        return seq < self._admitted_at.get(robot_id, 0)

    def forgoes(self, robot_id: str, seq: int) -> bool:
        """Whether this robot promised not to use ``robot_id``'s plan after task ``seq``."""
        return self._forgone.get(robot_id, seq + 1) <= seq

    def leave_out(self, robot_id: str, seq: int, why: str) -> None:
        """Teammate ``robot_id`` is down without a plan after task ``seq``: it
        is excluded from task ``seq + 1`` on, in a new epoch."""
        log.warning("%s is down (%s): excluded from task %d on", robot_id, why, seq + 1)
        self.excluded[robot_id] = seq + 1
        self.epoch += 1

    def grant(self, robot_id: str) -> str | None:
        """None if this robot grants teammate ``robot_id`` a lease (it counts
        it as up and a member), else why not.  Once refused, a process is
        never granted again: the others may be re-assigning its tasks
        (:mod:`coapkb.agent.lease`).  A teammate this robot has down is
        refused even while this robot is alone (:meth:`counts` counts it)."""
        if robot_id in self._peers and robot_id in self._teammates.down:
            return self._has_down(robot_id)
        why = self.counts(robot_id)
        if why is None and robot_id in self.refused:
            return f"{self.robot_id} had {robot_id} down: it never grants that process again"
        return why

    def counts(self, robot_id: str) -> str | None:
        """None if this robot counts teammate ``robot_id`` as up and a member,
        else why not: :meth:`grant` without the refusal of a process once
        down, which is about leases, not membership.  A teammate this robot
        has down while it is :attr:`alone` is counted: that suspicion is
        this robot's own, which hearing from it lifts
        (:class:`~.teammate_revival.TeammateRevival`), so two robots cut off
        from each other, each alone, still count each other again."""
        if robot_id not in self._peers:
            return f"{robot_id} is not in this robot's cluster"
        if robot_id in self.excluded or robot_id in self._forgone:
            return f"{self.robot_id} has left {robot_id} out of the membership"
        if robot_id in self._teammates.down and not self.alone:
            return self._has_down(robot_id)
        return None

    def _has_down(self, robot_id: str) -> str:
        return f"{self.robot_id} has {robot_id} down: {self._teammates.down[robot_id]}"

    @property
    def alone(self) -> bool:
        """Whether the members this robot counts as up, itself counted, are
        no majority of the cluster, while it has left nobody out: then it
        may be the one cut off, and decides nothing alone against teammates
        that may still count it (:meth:`.TeammateRevival.heard_again`).  A
        robot that left a teammate out has a membership of its own (another
        epoch): counting on the others again would not make it decide as
        they do (found in the simulator), and it stays as it is."""
        return not self.excluded and self.outnumbered

    @property
    def outnumbered(self) -> bool:
        """Whether the members this robot counts as up, itself counted, are
        no majority of the cluster."""
        up = sum(1 for r in self.members if r == self.robot_id or r not in self._teammates.down)
        return up <= (len(self._peers) + 1) // 2

    def admit(self, robot_id: str, seq: int, boot: int = 0) -> None:
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
        ahead of its teammate's on every task).

        ``boot``: the process that took the join at task ``seq`` (0: any,
        unless the feeder named it since, :meth:`named`).  Another process
        found there is a restart after it, down until it joins in turn
        (found in the simulator: a starved robot admitted a co-joiner that
        had died and started again since, and waited for a plan its new
        process, never given the join, never showed)."""
        if robot_id not in self._peers:
            return
        boot = self._named.pop((robot_id, seq), 0) or boot
        if boot == NO_PROCESS and robot_id in self.excluded:
            # The feeder said it did not take this join, and named it to no
            # teammate: they keep it out, in the same epoch, and so does this
            # robot (admitted, it ran one epoch ahead of them on every task
            # after: simulator seed 50615).
            log.warning("%s did not take its join at task %d: it stays out", robot_id, seq)
            return
        log.warning("%s joins the team again", robot_id)
        excluded_from = self.excluded.pop(robot_id, None)
        if excluded_from is not None:
            self.epoch += 1
            self._last_admission = _Admission(robot_id, seq, excluded_from, self.epoch)
        self._forgone.pop(robot_id, None)  # a promise about its old process
        self.refused.discard(robot_id)  # and a refusal of it
        self._admitted_at[robot_id] = seq
        self._named = {(r, s): b for (r, s), b in self._named.items() if s > self._admitted_at.get(r, 0)}
        self._teammates.readmit(robot_id, boot)

    async def missed(self, robot_id: str, seq: int, decided: bool = False) -> None:
        """The feeder says ``robot_id``, named a joiner at task ``seq``, did
        not take that post: no process of it joined there, so whichever
        this robot finds is another one, down until it joins at a later
        task; told before the admission, it is kept for it (found in the
        simulator, seed 467 of nine robots with power cuts), and a robot
        left out stays out (:meth:`admit`).  Told after an admission that
        let it in again, with nothing changed since and task ``seq`` not
        yet ``decided`` by this robot, the admission is undone: the
        teammates, never told of the join, keep the membership as it was."""
        last = self._last_admission
        if (not decided and last is not None and (last.robot_id, last.seq, last.epoch) == (robot_id, seq, self.epoch)
                and robot_id not in self.excluded):
            log.warning("%s did not take its join at task %d: it is out again", robot_id, seq)
            self.excluded[robot_id] = last.excluded_from
            self.epoch -= 1
            self._last_admission = None
        await self.named(robot_id, seq, NO_PROCESS)

    async def restarted(self, robot_id: str, seq: int) -> None:
        """The feeder says member ``robot_id`` ran again as a new process
        while task ``seq`` was posted or decided; the new one did not take
        it: the process this robot counts on is gone (down, and gone), and
        its last plan comes from a teammate that has it, as a dead robot's
        does; the new one joins at a later task.  A joiner that had never
        seen the old process took the new one for the member and waited for
        its plan for good (simulator, nine robots with power cuts, seed
        5563); a follower waited for its restarted leader's decision (seed
        3005 of the compute-and-communicate swarm profile).  Said of a task
        before this robot last admitted ``robot_id``, it is about the process
        that joined since, or an older one: a try of that post held back on
        the way and taken after the join had the robot count the member it
        had just admitted gone, and leave it out alone (seed 28 of three
        robots with messages held back and hedged retries)."""
        if self._before_admission(robot_id, seq):
            return
        if robot_id in self._peers and robot_id not in self.excluded and robot_id not in self._teammates.down:
            await self._teammates.process_gone(robot_id, f"restarted while task {seq} was decided")

    async def named(self, robot_id: str, seq: int, boot: int) -> None:
        """The feeder names process ``boot`` of ``robot_id`` as the one that
        took the join at task ``seq``, after the post (robots joining
        together learn each other's process from the post repeated, since
        the feeder knows them only from the joiners' answers)."""
        if robot_id not in self._peers or not boot:
            return
        admitted = self._admitted_at.get(robot_id, 0)
        if admitted == seq:
            await self._teammates.expect_process(robot_id, boot)
        elif admitted < seq:
            self._named[(robot_id, seq)] = boot

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

    async def join(self, seq: int, patience: float, joining: Sequence[str] = ()) -> Joined:
        """This robot (restarted) joins at task ``seq``: it takes the
        membership the teammates decided task ``seq - 1`` in
        (:func:`.joining.shown_to_join`; a new epoch, its admission, if that
        membership had left it out); its view then shows a plan right after
        ``seq - 1`` (:meth:`.TeamView.join`), which the others wait for
        before deciding ``seq``.

        ``joining``: every robot joining at ``seq`` (this one too).  When no
        process that decided ``seq - 1`` survives (each teammate is joining
        too, gone, or a new process that decided nothing) and no co-joiner
        joined on one, the joiners start a fresh membership of the join
        list, its epoch the task's number, the same on each (in the
        simulator, three robots restarted in turn decided nothing before).
        One past the task without this robot left it out: a membership of
        its own, alone, admitting nobody."""
        if seq <= 1:
            # Nothing decided before: the membership is the cluster's first.
            self._joined(seq, Membership(0, ()))
            return Joined(True, None)
        co_joiners = {r for r in joining if r in self._peers}
        shown, past = await shown_to_join(self._transport, self._endpoints, sorted(self._peers - co_joiners),
                                          sorted(co_joiners), seq, patience, self.robot_id)
        if shown is not None:
            plans_shown(self._teammates, self._peers - co_joiners, shown)
            self._joined(seq, Membership(shown.decision.epoch, shown.decision.members))
            return Joined(True, shown.decision)
        if past:
            # Left out by teammates that went on without it: a membership of
            # its own, alone (and fenced).  Its co-joiners may have joined
            # theirs: named here too, the lone membership looked a majority
            # to the feeder, and the cluster split (simulator seeds 314, 870
            # and 902 of the rejoin profile: two robots restarted in turn).
            log.warning("no teammate showed its decision of task %d (one is past it): left out, a membership of "
                        "its own", seq - 1)
            self._joined(seq, Membership(seq, (self.robot_id,)))
            return Joined(False, None)
        log.warning("no teammate showed its decision of task %d (none survives): a fresh membership of the robots "
                    "joining at task %d", seq - 1, seq)
        self._joined(seq, Membership(seq, tuple(sorted(co_joiners | {self.robot_id}))))
        return Joined(True, None)

    def _joined(self, seq: int, membership: Membership) -> None:
        """Join at task ``seq`` on top of ``membership`` (see :meth:`join`)."""
        self._last_admission = None
        if membership.members:
            gone = self._peers - set(membership.members)
            self.excluded = {r: seq - 1 for r in gone}
        # Its promises to go on without a member's plans were made while it
        # was out: the membership it takes counted that member since (found
        # in the simulator, seed 53530 of nine robots: a robot cut off, left
        # out and fed again left out a teammate the others had taken back,
        # on a promise of its first task, and decided in an epoch of its own).
        members = set(membership.members) or self._peers
        self._forgone = {r: s for r, s in self._forgone.items() if r not in members or s >= seq - 1}
        # Its admission is an epoch if that membership had left it out (see
        # :meth:`admit`); before any decision, nobody had.
        self.epoch = membership.epoch + (self.robot_id not in (membership.members or (self.robot_id,)))
        log.warning("joined the team at task %d (epoch %d, members %s)", seq, self.epoch, ", ".join(self.members))
