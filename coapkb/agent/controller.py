"""Controller (the seed's Fig. 2): runs the workflow for each task, in order.

Per task "pick up X" (seed section III-D): Query_1 (does X exist? if not,
every robot skips it), Query_2 (where is it; on a writable team also whether
it was picked or found missing: then every robot skips it too), Query_3 (its
features, how it is picked), Query_4 (which robots can pick it that way,
their payload).  An object the cluster already assigned is skipped without a
query: every robot of the cluster applied the same decisions.
With the compact wire Query_1 and Query_3 go to the Object KB's holder as
one exchange (``pick-facts``), and every query projects only what the
assigner reads; the seed's own system sends its four queries as printed.
Then the Task Assigner runs on the teammates' planned states, observed
through ``/robot/plan``, and the winner's Task Executor gets the job.

Strategies: "compute-by-all" (every robot queries and computes the same
assignment, no further message) and "compute-and-communicate" (the first
robot of the membership, the leader, computes and sends the decision to the
others).  A follower whose leader is declared down while it waits takes
the leader's decision from another follower that has it, or else decides
that task itself, as under compute-by-all: the assignment is a function of
the planned states after the previous task, which every survivor holds
alike, so it matches the decision the leader may have sent some of them
(the membership may not: without the leader's plan, the leader is left
out of it).
The dead leader leaves the membership as under compute-by-all, and the next
robot of it leads from then on.
"""

from __future__ import annotations

import asyncio
import logging
from collections import OrderedDict, deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, replace

from .. import clock
from ..config import RobotConfig
from ..transport.base import TransportError
from ..typed_fields import require_at_least
from ..world import DEPOT, travel_distance
from .cluster_claims import AskClaims, ClusterClaims
from .decisions import DecisionMessage, Task
from .facts import FactGatherer
from .job import Job
from .query_handler import ModuleUnavailable, QueryError, QueryHandler
from .robot_state import Decision, RobotState
from .settling import AskDecision, Settler
from .task_assigner import Assignment, TaskFacts, assign, robot_sort_key
from .task_executor import TaskExecutor
from .team_membership import Membership
from .team_view import TeamView

log = logging.getLogger(__name__)

#: Decisions kept whole (with the assignee's job) for teammates to take: they
#: ask about the task they are deciding, never about old ones.
RECENT_KEPT = 64


@dataclass(frozen=True)
class RobotBounds:
    """What a robot remembers per task, at most: a robot runs whole shifts."""

    #: Decisions shown on ``GET /tasks``: nothing but that listing reads past decisions.
    decisions_kept: int = 1024
    #: Objects whose assignment it remembers (:class:`Claim`): the last ones
    #: decided.  Older picks are in the KB by then (a writable team).
    claims_kept: int = 4096
    #: Claims a restarted robot takes from a teammate: a few minutes of tasks,
    #: by when a writable team has the picks in the KB (about 20 kB of CBOR).
    claims_handed: int = 512
    #: Task posts whose repeat it recognises (sequence numbers are consecutive).
    posts_remembered: int = 64

    def __post_init__(self) -> None:
        require_at_least(self, ("decisions_kept", "claims_kept", "claims_handed", "posts_remembered"))


#: A robot's bounds unless told otherwise.
DEFAULT_BOUNDS = RobotBounds()


def _sender(message: DecisionMessage) -> str | None:
    """The leader that sent ``message``, if it says its process: the first
    of the membership the decision was computed in."""
    members = message.decision.members
    return min(members, key=robot_sort_key) if message.boot and members else None


class Controller:
    def __init__(
        self,
        config: RobotConfig,
        queries: QueryHandler,
        team: TeamView,
        executor: TaskExecutor,
        publish: Callable[[RobotState], None],
        send_decision: Callable[[DecisionMessage], Awaitable[None]],
        ask_decision: AskDecision | None = None,
        ask_claims: AskClaims | None = None,
        bounds: RobotBounds = DEFAULT_BOUNDS,
    ) -> None:
        self.config = config
        self.bounds = bounds
        self.queries = queries
        self.team = team
        self.executor = executor
        self._publish = publish
        self._send_decision = send_decision
        #: This robot's last decisions as it applied them, by task: a teammate
        #: whose knowledge did not arrive takes one instead of deciding alone.
        self.recent: OrderedDict[int, DecisionMessage] = OrderedDict()
        self._tasks: asyncio.Queue[tuple[Task, float]] = asyncio.Queue()
        self._decisions: dict[int, asyncio.Future[DecisionMessage]] = {}
        #: The last ``bounds.decisions_kept`` decisions, oldest first (``GET /tasks``).
        self.log: deque[Decision] = deque(maxlen=bounds.decisions_kept)
        #: The same on every robot of the cluster, from the decisions applied.
        self.claims = ClusterClaims(bounds.claims_kept, bounds.claims_handed, ask_claims)
        self._runner: asyncio.Task[None] | None = None
        #: The task this robot joins its team again at (:meth:`rejoin_at`; 0: none).
        self._rejoins_at = 0
        #: What a task's decision needs from the KB.
        self.facts = FactGatherer(config, queries)
        #: Taking a teammate's decision when this robot cannot decide alone.
        self.settler = Settler(config.robot_id, team, config.query_timeout_s, ask_decision, self.recent,
                               fenced=executor.fenced)

    @property
    def robot_id(self) -> str:
        return self.config.robot_id

    @property
    def leader(self) -> str:
        """The robot that decides for the others ("compute and communicate"):
        the first of the current membership."""
        return min(self.team.membership.members, key=robot_sort_key)

    @property
    def computes(self) -> bool:
        return self.config.strategy == "compute-by-all" or self.robot_id == self.leader

    def start(self) -> None:
        self._runner = asyncio.create_task(self._run(), name="controller")

    async def aclose(self) -> None:
        if self._runner is not None:
            self._runner.cancel()
            try:
                await self._runner
            except asyncio.CancelledError:
                pass

    def submit(self, task: Task) -> None:
        """A new task from the feeder; tasks are handled strictly in order."""
        self._tasks.put_nowait((task, clock.monotonic()))

    def rejoin_at(self, seq: int) -> None:
        """This robot, left out by its teammates and fed nothing since, joins
        them again at task ``seq`` (its post taken): the tasks before it that
        it has not decided yet are not decided here, and their jobs, or any
        it holds, are not its own (the feeder sends them round again)."""
        self._rejoins_at = max(self._rejoins_at, seq)
        self.executor.void_before(seq, f"joined its team again at task {seq}: earlier tasks went round again")

    def receive_decision(self, message: DecisionMessage) -> None:
        """The leader's decision ("compute and communicate")."""
        future = self._decisions.setdefault(message.decision.seq, asyncio.get_running_loop().create_future())
        if not future.done():
            future.set_result(message)
        sender = _sender(message)
        if sender is not None:
            decision = message.decision
            self.team.revival.led_by(sender, message.boot, Membership(decision.epoch, decision.members))

    def _with_membership(self, decision: Decision) -> Decision:
        membership = self.team.membership
        return replace(decision, epoch=membership.epoch, members=membership.members)

    async def _run(self) -> None:
        while True:
            task, received = await self._tasks.get()
            if task.seq < self._rejoins_at:
                log.warning("task %d (%s): not decided: this robot joins its team again at task %d",
                            task.seq, task.object, self._rejoins_at)
                continue
            try:
                await self._admit(task)
                if task.again is not None or task.restocked:
                    # Never picked, or back on its shelf: the object is free again, on every robot alike.
                    self.claims.pop(task.object, None)
                message = await self._decide(task, received)
            except ModuleUnavailable as exc:
                # Not an error of this robot: every teammate without the module
                # finds the same, and the record says why the task waits.
                log.warning("task %d (%s): %s", task.seq, task.object, exc)
                alone = DecisionMessage(Decision(task.seq, task.object, unavailable=str(exc)))
                message = await self.settler.settle(task, alone)
                if message is alone:
                    message = await self._read_elsewhere(task, received, exc) or alone
            except (QueryError, TransportError) as exc:
                log.error("task %d (%s): %s", task.seq, task.object, exc)
                message = await self.settler.settle(task, DecisionMessage(Decision(task.seq, task.object, error=str(exc))))
            except Exception as exc:  # keep the robot alive and the team informed
                log.exception("task %d (%s) failed", task.seq, task.object)
                message = DecisionMessage(Decision(task.seq, task.object, error=f"internal error: {exc}"))
            coordination_s = round(clock.monotonic() - received, 6)
            decision = replace(message.decision, coordination_s=coordination_s)
            if not decision.members:  # not the leader's, stamped already
                decision = self._with_membership(decision)
            self._apply(replace(message, decision=decision))

    async def _read_elsewhere(self, task: Task, received: float, lost: ModuleUnavailable) -> DecisionMessage | None:
        """``task`` decided again on knowledge once the holder the cluster
        read ``lost.module`` from was found down while this robot settled
        the task, and the cluster reads from another now: every survivor
        that settled without it reads there alike (one that does not find
        it down yet takes their decision as it settles).  Deciding nothing
        instead split the cluster from the robot that had decided just
        before it froze, on that holder's knowledge, which the next holder
        most likely shares (found in the simulator, seeds 2271 and 2619: the
        holder frozen 17-20 s).  None if no other holder is live."""
        now = self.queries.reads_from(lost.module)
        if now is None or now in lost.why:
            return None
        log.warning("task %d (%s): the %s KB is read from %s now; deciding again", task.seq, task.object,
                    lost.module, now)
        if (settled := await self.settler.decided_by_teammates(task)) is not None:
            return settled
        try:
            return await self._decide(task, received)
        except (QueryError, TransportError) as exc:
            log.warning("task %d (%s): deciding again failed too: %s", task.seq, task.object, exc)
            # A teammate that read there may have decided on knowledge
            # meanwhile: taken, as any settling takes it (found in the
            # simulator, seed 3296: the answers of the next holder lost here,
            # not there, and the two decided differently).
            why = str(exc)
            again = DecisionMessage(Decision(task.seq, task.object, unavailable=why)
                                    if isinstance(exc, ModuleUnavailable) else Decision(task.seq, task.object, error=why))
            settled = await self.settler.settle(task, again)
            return None if settled is again else settled

    def _apply(self, message: DecisionMessage) -> None:
        decision = message.decision
        me = self.team.own
        plan = me.plan
        if decision.assigned_to == self.robot_id and message.after is not None and message.job is not None:
            plan = message.after
            self.executor.submit(message.job)
        self.log.append(decision)
        self.team.used_plans(decision)
        self.claims.record(decision)
        self.recent[decision.seq] = message
        while len(self.recent) > RECENT_KEPT:
            self.recent.popitem(last=False)
        self.team.set_own(me.with_plan(replace(plan, seq=decision.seq), decision))
        self._publish(self.team.own)
        log.info(
            "task %d %s: %s", decision.seq, decision.object,
            decision.error or decision.unavailable
            or (f"skipped ({decision.skip_reason})" if decision.skipped else f"-> {decision.assigned_to}"),
        )

    async def _admit(self, task: Task) -> None:
        """Joins take effect at their task, in task order, on every robot:
        one epoch each on top of the membership of the task before.  A robot
        that joins takes that membership first, then admits the others
        joining with it (admitted first, they were lost when it took the
        membership: two robots back at one task named different epochs,
        found in the simulator).  Joiners with no surviving teammate, none
        of them joined on one's decision, start a fresh membership of the
        join list (:meth:`.TeamMembership.join`) and admit each other on it
        alike."""
        if self.robot_id in task.join:
            if task.seq == self._rejoins_at:
                # Not a new process: one its teammates had left out, fed
                # again from this task (:meth:`rejoin_at`).  Its suspicions
                # are of a membership it leaves.
                self.team.forget_suspicions()
            joined = await self.team.join(task.seq, patience=self.config.query_timeout_s, joining=task.join)
            # Before its plan is out, nobody has decided this task: the
            # claims a teammate hands over are those of the tasks before it.
            await self._take_claims(task.seq)
            self._publish(self.team.own)
            if not joined:
                return  # left out, alone: its co-joiners may be in the cluster's membership
        for robot_id in task.join:
            if robot_id != self.robot_id:
                self.team.membership.admit(robot_id, task.seq, task.boots.get(robot_id, 0))

    async def _take_claims(self, seq: int) -> None:
        """A restarted robot joining at task ``seq`` takes the cluster's
        claims of the tasks before from a live teammate (the last
        ``bounds.claims_handed``), so it skips a repeat as they do."""
        members = [r for r in sorted(self.team.membership.members, key=robot_sort_key)
                   if r != self.robot_id and self.team.is_up(r)]
        # Then the rest of the cluster: a joiner that started a membership
        # of its own still skips what the cluster gave (found in the
        # simulator: a joiner its teammates had left out, alone in its
        # membership, gave an object again).
        await self.claims.take(seq, [*members, *(r for r in self.team.teammates if r not in members)])

    async def _decide(self, task: Task, received: float) -> DecisionMessage:
        if not self.computes:
            return await self._await_decision(task, received)
        if self.config.strategy == "compute-by-all":
            theirs = await self.settler.decided_before(task, received)
            if theirs is not None:
                return theirs
        message = await self._compute(task)
        if self.config.strategy == "compute-and-communicate":
            # Stamped with the membership it was computed in: the followers
            # take it as theirs (a follower's own view of who is down lags).
            message = replace(message, decision=self._with_membership(message.decision), boot=self.team.own.boot)
            try:
                await self._send_decision(message)
            except TransportError as exc:  # the decision stands; the teammate reports its own timeout
                log.error("%s", exc)
        return message

    async def _await_decision(self, task: Task, received: float) -> DecisionMessage:
        """The leader's decision on ``task``; if the leader is declared down
        first, this robot's own (see the module's docstring)."""
        leader = self.leader
        future = self._decisions.setdefault(task.seq, asyncio.get_running_loop().create_future())
        leader_down = asyncio.create_task(self.team.until_down(leader), name=f"leader {leader} down")
        try:
            async with asyncio.timeout(self.config.query_timeout_s * 4):
                await asyncio.wait((future, leader_down), return_when=asyncio.FIRST_COMPLETED)
        except TimeoutError:
            raise QueryError(f"no decision from {leader} for task {task.seq}") from None
        finally:
            leader_down.cancel()
            self._decisions.pop(task.seq, None)
        if future.done():
            message = future.result()
            self.team.membership.adopt(Membership(message.decision.epoch, message.decision.members), task.seq)
            sender = _sender(message)
            if sender is not None:
                self.team.saw_process(sender, message.boot)
            return message
        log.warning("task %d: the leader %s is down (%s); deciding it here", task.seq, leader, leader_down.result())
        taken = await self.settler.leaders_decision(task, leader)
        if taken is not None:
            return taken
        computed = await self._compute(task)
        # A follower that decided it meanwhile, or while this one stood
        # still, settled it: frozen while it computed, one took the dead
        # leader's last plan that the other, asking it in vain, had done
        # without (simulator, seed 14580 of the compute-and-communicate
        # swarm profile: one task in two epochs).
        return await self.settler.decided_before(task, received) or computed

    async def gather(self, task: Task) -> TaskFacts | str:
        """What the task's pick needs from the KBs, or why nobody picks it;
        an object the cluster assigned already is skipped without a query."""
        claim = self.claims.get(task.object)
        if claim is not None:  # decided here, perhaps not yet picked: no need to ask
            return str(claim)
        return await self.facts.gather(task)

    async def _compute(self, task: Task) -> DecisionMessage:
        started = clock.monotonic()
        facts = await self.gather(task)
        if isinstance(facts, str):
            return DecisionMessage(Decision(task.seq, task.object, skipped=True, skip_reason=facts))
        layout, energy, docks = await self.facts.layout(), await self.facts.energy(), await self.facts.docks()
        gathered = clock.monotonic()
        states = await self.team.planned_states(task.seq - 1, timeout=self.config.query_timeout_s * 2)
        # Where a slow task's time went (coapkb bench --trace keeps these).
        log.info("task %d: KB answers in %.3f s, teammates' plans %.3f s later",
                 task.seq, gathered - started, clock.monotonic() - gathered)
        result: Assignment = assign(
            facts, states, energy, lambda a, b: travel_distance(a, b, layout), DEPOT, self.config.cost, docks
        )
        decision = Decision(
            task.seq, task.object, assigned_to=result.assigned_to, costs=result.costs, reasons=result.reasons
        )
        if result.plan is None:
            return DecisionMessage(decision)
        plan = result.plan
        job = Job(
            task.seq, task.object, facts.aisle, facts.rack, plan.to_object_m, plan.to_depot_m,
            (DEPOT.aisle, DEPOT.rack), plan.charge, plan.after.battery_wh, plan.after.load_kg,
        )
        return DecisionMessage(decision, plan.after, job)
