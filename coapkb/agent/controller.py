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
others).  A follower whose leader is declared down while it waits decides
that task itself, as under compute-by-all: the assignment is a function of
the planned states after the previous task, which every survivor holds
alike, so it matches the decision the leader may have sent some of them.
The dead leader leaves the membership as under compute-by-all, and the next
robot of it leads from then on.
"""

from __future__ import annotations

import asyncio
import logging
from collections import OrderedDict, deque
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import asdict, dataclass, replace

import cbor2

from .. import clock
from ..config import RobotConfig
from ..kb.named_queries import MAX_LIST_ITEMS
from ..model.results import SelectResult
from ..transport.base import PeerGone, TransportError
from ..world import Layout, Position, layout_from_row, travel_distance
from .job import Job
from .query_handler import ModuleUnavailable, QueryError, QueryHandler
from .robot_state import Decision, PlannedState, RobotState
from .task_assigner import Assignment, ChargeStop, RobotEnergy, TaskFacts, assign, robot_sort_key
from .task_executor import TaskExecutor
from .team_view import Membership, TeamView

log = logging.getLogger(__name__)

#: The depot, where robots unload: the front end of the first aisle.
DEPOT = Position(1, 0)
#: Decisions a robot keeps to show on ``GET /tasks``: a robot runs whole shifts,
#: and nothing but that listing reads its past decisions.
DECISIONS_KEPT = 1024
#: Decisions kept whole (with the assignee's job) for teammates to take: they
#: ask about the task they are deciding, never about old ones.
RECENT_KEPT = 64
#: Where a robot serves its cluster's claims (:func:`encode_claims`).
CLAIMS_PATH = "/robot/claims"
#: How often a robot whose knowledge did not arrive asks its teammates again.
SETTLE_POLL_S = 0.5
#: How long it asks, in query timeouts; and while a teammate answers that it
#: is still deciding the task, how long at most.
SETTLE_WAIT_TIMEOUTS = 2
SETTLE_DECIDING_TIMEOUTS = 6
#: Objects whose assignment a robot remembers (:class:`Claim`): the last
#: ones decided.  Older picks are in the KB by then (a writable team).
CLAIMS_KEPT = 4096
#: Claims a restarted robot takes from a teammate: a few minutes of tasks,
#: by when a writable team has the picks in the KB (about 20 kB of CBOR).
CLAIMS_HANDED = 512
#: The skip reason of an object no KB knows.
NO_SUCH_OBJECT = "no such object"


@dataclass(frozen=True)
class Claim:
    """An object this robot's cluster assigned: to whom, at which task."""

    robot: str
    seq: int

    def __str__(self) -> str:
        return f"picked by {self.robot} at task {self.seq}"


@dataclass(frozen=True)
class Task:
    seq: int
    object: str
    #: Robots (restarted) that are members again from this task on.
    join: tuple[str, ...] = ()
    #: The task this one does again: its robot went down before the pick.
    again: int | None = None
    #: The object was delivered back to its shelf since the cluster decided
    #: it (coapkb.feeder.restock): the claim remembered is void.
    restocked: bool = False


@dataclass(frozen=True)
class DecisionMessage:
    """What "compute and communicate" sends: the decision and the winner's plan."""

    decision: Decision
    after: PlannedState | None = None
    job: Job | None = None
    #: The sending leader's process (:attr:`RobotState.boot`; 0 = not said):
    #: a follower that never observed it can still tell a new process of it.
    boot: int = 0

    def to_dict(self) -> dict:
        raw: dict[str, object] = {
            "decision": asdict(self.decision),
            "after": asdict(self.after) if self.after else None,
            "job": asdict(self.job) if self.job else None,
        }
        if self.boot:
            raw["boot"] = self.boot
        return raw

    @classmethod
    def from_dict(cls, raw: Mapping) -> DecisionMessage:
        job = raw.get("job")
        return cls(
            decision=Decision(**raw["decision"]),
            after=PlannedState(**raw["after"]) if raw.get("after") else None,
            job=_job(job) if job else None,
            boot=int(raw.get("boot", 0)),
        )


def _job(raw: Mapping) -> Job:
    charge = raw.get("charge")
    if charge is not None:
        charge = ChargeStop(**{**charge, "dock": Position(**charge["dock"])})
    return Job(**{**raw, "depot": tuple(raw["depot"]), "charge": charge})


def _first(result: object, name: str) -> list[dict]:
    if not isinstance(result, SelectResult):
        raise QueryError(f"{name} did not return solutions")
    return result.as_dicts()


class Controller:
    def __init__(
        self,
        config: RobotConfig,
        queries: QueryHandler,
        team: TeamView,
        executor: TaskExecutor,
        publish: Callable[[RobotState], None],
        send_decision: Callable[[DecisionMessage], Awaitable[None]],
        ask_decision: Callable[[str, int], Awaitable[DecisionMessage | None]] | None = None,
        ask_claims: Callable[[str], Awaitable[dict[str, Claim]]] | None = None,
    ) -> None:
        self.config = config
        self.queries = queries
        self.team = team
        self.executor = executor
        self._publish = publish
        self._send_decision = send_decision
        #: Asks a teammate for its decision on a task (None: it has none yet;
        #: TransportError: it does not answer).
        self._ask_decision = ask_decision
        #: Asks a teammate for the cluster's claims (a restarted robot joining).
        self._ask_claims = ask_claims
        #: This robot's last decisions as it applied them, by task: a teammate
        #: whose knowledge did not arrive takes one instead of deciding alone.
        self.recent: OrderedDict[int, DecisionMessage] = OrderedDict()
        self._tasks: asyncio.Queue[tuple[Task, float]] = asyncio.Queue()
        self._decisions: dict[int, asyncio.Future[DecisionMessage]] = {}
        self._layout: Layout | None = None
        self._energy: dict[str, RobotEnergy] | None = None
        self._docks: tuple[Position, ...] | None = None
        #: The last ``DECISIONS_KEPT`` decisions, oldest first (``GET /tasks``).
        self.log: deque[Decision] = deque(maxlen=DECISIONS_KEPT)
        #: object -> the cluster's assignment of it, from the decisions
        #: applied: the same on every robot of the cluster, so a repeat is
        #: skipped alike before the pick is written (or even made).
        self.claims: OrderedDict[str, Claim] = OrderedDict()
        self._runner: asyncio.Task | None = None

    @property
    def robot_id(self) -> str:
        return self.config.robot_id

    async def _about_team(self, query: str, params: Mapping[str, str]) -> list[dict]:
        """``query`` for this robot's team only (its ``-among`` form: the answer
        does not grow with the fleet in the KB), or for every robot when the
        team is longer than a list parameter takes.  The team is in one order
        on every robot, so a teammate's answer cache serves it once."""
        team = sorted(self.config.team, key=robot_sort_key)
        if len(team) <= MAX_LIST_ITEMS:
            query, params = f"{query}-among", {**params, "robots": ",".join(team)}
        return _first(await self.queries.run(query, params), query)

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

    def receive_decision(self, message: DecisionMessage) -> None:
        """The leader's decision ("compute and communicate")."""
        future = self._decisions.setdefault(message.decision.seq, asyncio.get_running_loop().create_future())
        if not future.done():
            future.set_result(message)

    def _with_membership(self, decision: Decision) -> Decision:
        membership = self.team.membership
        return replace(decision, epoch=membership.epoch, members=membership.members)

    async def _run(self) -> None:
        while True:
            task, received = await self._tasks.get()
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
                message = await self._settle(task, alone)
                if message is alone:
                    message = await self._read_elsewhere(task, received, exc) or alone
            except (QueryError, TransportError) as exc:
                log.error("task %d (%s): %s", task.seq, task.object, exc)
                message = await self._settle(task, DecisionMessage(Decision(task.seq, task.object, error=str(exc))))
            except Exception as exc:  # keep the robot alive and the team informed
                log.exception("task %d (%s) failed", task.seq, task.object)
                message = DecisionMessage(Decision(task.seq, task.object, error=f"internal error: {exc}"))
            coordination_s = round(clock.monotonic() - received, 6)
            decision = replace(message.decision, coordination_s=coordination_s)
            if not decision.members:  # not the leader's, stamped already
                decision = self._with_membership(decision)
            self._apply(replace(message, decision=decision))

    async def _settle(self, task: Task, alone: DecisionMessage) -> DecisionMessage:
        """The decision on ``task`` when this robot's own knowledge did not
        arrive (a lost answer, a holder that seemed down): a live teammate's
        decided on knowledge, taken whole, so every robot decides alike;
        ``alone`` (unavailable, or an error) if every live teammate failed
        too, or none decided within the wait (:data:`SETTLE_WAIT_TIMEOUTS`
        query timeouts, up to :data:`SETTLE_DECIDING_TIMEOUTS` while one
        answers that it has not decided yet).  Meanwhile teammates asking
        this robot get ``alone``: two robots that both failed do not wait
        for each other."""
        self.recent[task.seq] = alone
        if self._ask_decision is None:
            return alone
        started = clock.monotonic()
        deadline = started + self.config.query_timeout_s * SETTLE_WAIT_TIMEOUTS
        last_call = started + self.config.query_timeout_s * SETTLE_DECIDING_TIMEOUTS
        deciding = unanswered = False
        # Past the deadline only while a teammate says it is still deciding,
        # or while one that is up has not answered yet: a round can end past
        # the deadline (a frozen teammate's ask runs out, then the indirect
        # probe that finds it back), and ending there would decide alone
        # against a teammate that, asked by it meanwhile, saw this robot's
        # undecided answer and decided on its own knowledge (found in the
        # simulator: a robot frozen 14-17 s, the only holder of a module).
        while clock.monotonic() < (last_call if deciding or unanswered else deadline):
            # A teammate whose answer was just lost is asked too: it may be the
            # one that had the knowledge (found in the simulator).  A robot
            # with no majority up asks the members it has down as well: it may
            # be the one that was cut off, and they went on counting it (found
            # in the simulator: after the heal it decided every task alone
            # while they assigned it tasks).  One that answers is counted on again.
            outnumbered = self.team.alone
            mates = [r for r in self.team.membership.members
                     if r != self.robot_id and (outnumbered or self.team.is_up(r))]
            answers = await asyncio.gather(*(self._ask_decision(mate, task.seq) for mate in mates),
                                           return_exceptions=True)
            heard = [mate for mate, theirs in zip(mates, answers)
                     if not isinstance(theirs, BaseException) and not self.team.is_up(mate)]
            if heard:
                await asyncio.gather(*(self.team.heard_again(mate) for mate in heard))
            failed_too = 0
            deciding = unanswered = False
            for mate, theirs in zip(mates, answers):
                if isinstance(theirs, BaseException):
                    # A lost answer is asked again (found in the simulator:
                    # three asks lost at 20 % loss, and this robot decided
                    # alone); the failure counts like a probe's, so a dead
                    # teammate is soon known down, and cannot help.
                    if isinstance(theirs, TransportError):
                        await self.team.request_failed(mate, theirs)
                    # Outnumbered, a silence is no answer: the silent ones may
                    # be the majority, cut off from this robot, and it waits
                    # for them; only a teammate whose process is gone cannot help.
                    failed_too += not self.team.is_up(mate) and (not outnumbered or isinstance(theirs, PeerGone))
                    unanswered = unanswered or self.team.is_up(mate)
                    continue
                if theirs is None or theirs.decision.object != task.object:
                    # Still deciding: waited for past the deadline (found in
                    # the simulator: a robot gave up the moment before a
                    # teammate back from a partition decided on knowledge).
                    deciding = True
                    continue
                if not self._counts_me(theirs.decision):
                    # Decided in a membership without this robot: not taken
                    # (it would name their epoch, and its next decisions,
                    # its own, would then not be void).
                    failed_too += 1
                    continue
                if theirs.decision.error is None and theirs.decision.unavailable is None:
                    log.warning("task %d (%s): its knowledge did not reach this robot; took %s's decision",
                                task.seq, task.object, mate)
                    # And the membership it was taken in: this robot's own
                    # view may not have caught up (it computed nothing), and
                    # the next join counts its epoch from there (found in
                    # the simulator).
                    self.team.adopt(Membership(theirs.decision.epoch, theirs.decision.members), task.seq)
                    return theirs
                failed_too += 1
            if failed_too == len(mates):  # nobody had the knowledge: every robot alike
                return alone
            await asyncio.sleep(SETTLE_POLL_S)
        return alone

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
            settled = await self._settle(task, again)
            return None if settled is again else settled

    def _apply(self, message: DecisionMessage) -> None:
        decision = message.decision
        me = self.team.own
        plan = me.plan
        if decision.assigned_to == self.robot_id and message.after is not None and message.job is not None:
            plan = message.after
            self.executor.submit(message.job)
        self.log.append(decision)
        if decision.assigned_to is not None:
            self.claims[decision.object] = Claim(decision.assigned_to, decision.seq)
            self.claims.move_to_end(decision.object)
            while len(self.claims) > CLAIMS_KEPT:
                self.claims.popitem(last=False)
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
        found in the simulator).  Joiners with no surviving teammate start a
        fresh membership of the join list (:meth:`TeamView.join`) and admit
        each other on it alike."""
        if self.robot_id in task.join:
            await self.team.join(task.seq, timeout=self.config.query_timeout_s * 4, joining=task.join)
            # Before its plan is out, nobody has decided this task: the
            # claims a teammate hands over are those of the tasks before it.
            await self._take_claims(task.seq)
            self._publish(self.team.own)
        for robot_id in task.join:
            if robot_id != self.robot_id:
                self.team.admit(robot_id)

    async def _take_claims(self, seq: int) -> None:
        """A restarted robot joining at task ``seq`` takes the cluster's
        claims of the tasks before from a live teammate (the last
        ``CLAIMS_HANDED``), so it skips a repeat as they do."""
        if self._ask_claims is None:
            return
        for mate in sorted(self.team.membership.members, key=robot_sort_key):
            if mate == self.robot_id or not self.team.is_up(mate):
                continue
            try:
                claims = await self._ask_claims(mate)
            except TransportError as exc:
                log.warning("task %d: no claims from %s: %s", seq, mate, exc)
                continue
            # A teammate that saw this robot's plan may have decided this
            # task already: its claim of it is not one of the tasks before.
            earlier = sorted(((o, c) for o, c in claims.items() if c.seq < seq), key=lambda item: item[1].seq)
            self.claims = OrderedDict(earlier)
            log.info("task %d: took %d claims from %s", seq, len(claims), mate)
            return
        log.warning("task %d: no teammate handed its claims over: a repeat of an earlier object may be decided "
                    "differently here", seq)

    def claims_handed(self) -> dict[str, Claim]:
        """The claims a restarted teammate takes: the latest ``CLAIMS_HANDED``."""
        latest = list(self.claims.items())[-CLAIMS_HANDED:]
        return dict(latest)

    async def _decide(self, task: Task, received: float) -> DecisionMessage:
        if not self.computes:
            return await self._await_decision(task)
        if self.config.strategy == "compute-by-all":
            theirs = await self._decided_before_me(task, received)
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

    async def _decided_before_me(self, task: Task, received: float) -> DecisionMessage | None:
        """A teammate's decision on ``task`` if one may have decided it before
        this robot began it: its observed plan is past the task already, or
        this process stood still for a request timeout or more since about
        when the task came (its teammates' requests to it went unanswered
        meanwhile, and the observations of their plans may have been dropped).
        This robot lags behind, and what it would compute now may not be what
        they settled.  Found in the simulator: a robot frozen in a pick for
        20 s, the one the Location KB's places are read from, while its
        teammates settled a task unavailable without it; back, it decided the
        task alone on its own knowledge and picked it, and the record said
        failed.  The decision is taken whole, as :meth:`_settle` takes one:
        one decided on knowledge first, else one settled unavailable (and
        applied); none decided in a membership without this robot (its own
        decision is void then).  A robot in step asks nothing: no extra
        message per task."""
        if self._ask_decision is None:
            return None
        mates = [r for r in self.team.membership.members if r != self.robot_id and self.team.is_up(r)]
        window = clock.monotonic() - received + self.config.query_timeout_s * 2
        if self.team.stalled_within(window) >= self.team.request_timeout_s:
            ahead = mates
        else:
            ahead = [r for r in mates if (state := self.team.state_of(r)) is not None and state.plan.seq >= task.seq]
        if not ahead:
            return None
        answers = await asyncio.gather(*(self._ask_decision(mate, task.seq) for mate in ahead),
                                       return_exceptions=True)
        # An unavailable one still being settled (not yet applied, so not
        # stamped with its members) may yet give way to a decision on knowledge.
        taken = [(mate, theirs) for mate, theirs in zip(ahead, answers)
                 if isinstance(theirs, DecisionMessage) and theirs.decision.object == task.object
                 and theirs.decision.error is None and self._counts_me(theirs.decision)
                 and (theirs.decision.unavailable is None or theirs.decision.members)]
        taken.sort(key=lambda item: item[1].decision.unavailable is not None)  # on knowledge first
        if not taken:
            return None
        mate, theirs = taken[0]
        log.warning("task %d (%s): %s decided it before this robot began; took its decision",
                    task.seq, task.object, mate)
        self.team.adopt(Membership(theirs.decision.epoch, theirs.decision.members), task.seq)
        return theirs

    def _counts_me(self, decision: Decision) -> bool:
        """Whether ``decision`` was taken in a membership with this robot in it."""
        return not decision.members or self.robot_id in decision.members

    async def _await_decision(self, task: Task) -> DecisionMessage:
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
            self.team.adopt(Membership(message.decision.epoch, message.decision.members), task.seq)
            if message.boot and message.decision.members:
                # Its sender: the first of the membership it was computed in.
                self.team.saw_process(min(message.decision.members, key=robot_sort_key), message.boot)
            return message
        log.warning("task %d: the leader %s is down (%s); deciding it here", task.seq, leader, leader_down.result())
        return await self._compute(task)

    async def layout(self) -> Layout:
        if self._layout is None:
            rows = _first(await self.queries.run("warehouse-layout", {}), "warehouse-layout")
            if not rows:
                raise QueryError("the Location KB has no warehouse layout")
            self._layout = layout_from_row(rows[0])
        return self._layout

    async def docks(self) -> tuple[Position, ...]:
        """The charging docks, asked once of the Location KB (in its order:
        the tie-break between equally good docks)."""
        if self._docks is None:
            rows = _first(await self.queries.run("charging-docks", {}), "charging-docks")
            self._docks = tuple(Position(int(r["aisle_no"]), int(r["rack_no"])) for r in rows)
        return self._docks

    async def energy(self) -> dict[str, RobotEnergy]:
        """Every teammate's energy figures, asked once of the Capability KB."""
        if self._energy is None:
            rows = await self._about_team("robot-specs", {})
            self._energy = {
                str(r["robo_id"]): RobotEnergy(
                    float(r["e_empty"]), float(r["e_loaded"]), float(r["e_pick"]), float(r["battery"])
                )
                for r in rows
                if str(r["robo_id"]) in self.config.team
            }
        return self._energy

    async def gather(self, task: Task) -> TaskFacts | str:
        """What the task's pick needs from the KBs, or why nobody picks it:
        no such object, already picked (by whom, at which task), missing."""
        claim = self.claims.get(task.object)
        if claim is not None:  # decided here, perhaps not yet picked: no need to ask
            return str(claim)
        params = {"name": task.object}
        if self.queries.wire == "seed":
            exists, where, features = await self._seed_queries(params)
        else:
            # One exchange per KB holder: existence, grip and weight from the
            # Object KB, the place and what became of the object from the
            # Location KB (``pick-facts`` and ``pick-place``: the seed's
            # Query_1-3 as the assigner uses them).  The place is read as the
            # holder first told it for this task: every robot alike.
            exists, where = (
                _first(rows, label)
                for rows, label in zip(
                    await asyncio.gather(self.queries.run("pick-facts", params),
                                         self.queries.run("pick-place", params, at=task.seq)),
                    ("pick-facts", "pick-place"),
                )
            )
            features = [row for row in exists if row.get("grip") is not None and row.get("weight") is not None]
            why = _gone(where)
            if exists and why is not None:
                return why
            where = [row for row in where if row.get("aisle_no") is not None]
        if not exists:
            return NO_SUCH_OBJECT
        if not where or not features:
            # Said apart: a new product written into the Object KB alone has
            # its features but no shelf yet.
            lacking = [what for what, missing in (
                ("no place (aisle, rack, bin) in the Location KB", not where),
                ("no grip and weight in the Object KB" if self.queries.wire != "seed"
                 else "not every feature Query_3 asks in the Object KB", not features),
            ) if missing]
            raise QueryError(f"{task.object} exists but has {' and '.join(lacking)}")
        grip = _local_name(features[0]["grip"])
        robots = await self._about_team("robots-for-grip", {"grip": grip})
        capable = {str(r["robo_id"]): float(r["payload"]) for r in robots if str(r["robo_id"]) in self.config.team}
        return TaskFacts(
            seq=task.seq,
            object=task.object,
            aisle=int(where[0]["aisle_no"]),
            rack=int(where[0]["rack_no"]),
            bin=int(where[0]["bin_no"]),
            weight_kg=float(features[0]["weight"]),
            grip=grip,
            capable=capable,
        )

    async def _seed_queries(self, params: Mapping[str, str]) -> tuple[list[dict], ...]:
        """The seed's Query_1, Query_2 and Query_3, as its system sends them."""
        # Query_2 and Query_3 need only the name, so they go out with Query_1
        # (the transports keep several exchanges in flight): two round trips
        # on the critical path instead of four.  For an object that does not
        # exist their empty answers are simply dropped.
        answers = await asyncio.gather(
            self.queries.run("object-exists", params),
            self.queries.run("object-location", params),
            self.queries.run("object-features", params),
        )
        return tuple(_first(rows, label) for rows, label in zip(answers, ("Query_1", "Query_2", "Query_3")))

    async def _compute(self, task: Task) -> DecisionMessage:
        started = clock.monotonic()
        facts = await self.gather(task)
        if isinstance(facts, str):
            return DecisionMessage(Decision(task.seq, task.object, skipped=True, skip_reason=facts))
        layout, energy, docks = await self.layout(), await self.energy(), await self.docks()
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


def encode_claims(claims: Mapping[str, Claim]) -> bytes:
    """``/robot/claims``: ``[[object, robot, seq], ...]`` in CBOR."""
    return cbor2.dumps([[obj, c.robot, c.seq] for obj, c in claims.items()])


def decode_claims(payload: bytes) -> dict[str, Claim]:
    """:func:`encode_claims`'s output; ``ValueError`` for anything else."""
    try:
        raw = cbor2.loads(payload)
    except (cbor2.CBORDecodeError, RecursionError) as exc:
        raise ValueError(f"not CBOR: {exc}") from None
    if not isinstance(raw, list):
        raise ValueError("claims are an array")
    claims = {}
    for item in raw:
        if not (isinstance(item, list) and len(item) == 3 and isinstance(item[0], str) and isinstance(item[1], str)
                and type(item[2]) is int and item[2] > 0):
            raise ValueError(f"a claim is [object, robot, seq], got {item!r}"[:200])
        claims[item[0]] = Claim(item[1], item[2])
    return claims


def _gone(rows: list[dict]) -> str | None:
    """What ``pick-place`` says became of an object: picked (by whom, at
    which task) or missing from its place; None if it is on its shelf."""
    for row in rows:
        if row.get("picked_by") is not None:
            return f"picked by {row['picked_by']} at task {row.get('picked_task')}"
    for row in rows:
        if row.get("missing_task") is not None and row.get("aisle_no") is None:
            return f"missing from its place since task {row['missing_task']}"
    return None


def _local_name(term: object) -> str:
    text = str(term)
    return text.rsplit("#", 1)[-1].rsplit("/", 1)[-1]
