"""Controller: the seed's four queries per task, the barrier on the teammates'
planned states, both strategies, and how failures become a decision's error.
Teammates are routers on the in-memory transport; no processes."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Mapping

import pytest
from agent_helpers import config, endpoint

from coapkb.agent.controller import Controller
from coapkb.agent.decisions import DecisionMessage, Task
from coapkb.agent.observed_states import PLAN_PATH
from coapkb.agent.query_handler import QueryError, QueryHandler
from coapkb.agent.robot_state import Decision, LiveState, PlannedState, RobotState
from coapkb.agent.settling import Settler
from coapkb.agent.task_executor import TaskExecutor
from coapkb.agent.team_membership import Membership
from coapkb.agent.team_view import TeamView
from coapkb.config import RobotConfig
from coapkb.kb.client import KBClient
from coapkb.kb.store import KnowledgeBase
from coapkb.model.results import SelectResult
from coapkb.transport.base import PeerGone, PeerTimeout, ResourceInfo, TransportError
from coapkb.transport.memory import MemoryNetwork
from coapkb.transport.messages import ContentFormat, Request, Response, Status
from coapkb.transport.router import Router

ALL = ("Location", "Object", "Capability")
#: Robot1 answers every query itself; Robot2 is a teammate with no KB.
PAIR = {"Robot1": ALL, "Robot2": ()}
OBJECT = "Gucci_bag_14"
OTHER_OBJECT = "Barilla_pasta_1"


def _state(robot_id: str, seq: int = 0, aisle: int = 1) -> RobotState:
    return RobotState(robot_id, PlannedState(aisle, 0, 400.0, 0.0, 60.0, seq), LiveState(float(aisle), 0.0))


class Teammate:
    """A teammate that only publishes its planned state on /robot/plan."""

    def __init__(self, robot_id: str) -> None:
        self.state = _state(robot_id)
        self.router = Router()
        self.router.add(ResourceInfo(PLAN_PATH, obs=True), self._get)

    async def _get(self, request: Request) -> Response:
        return Response(Status.CONTENT, self.state.encode_plan(), ContentFormat.CBOR)

    def decide(self, seq: int) -> None:
        self.state = self.state.with_plan(PlannedState(1, 0, 400.0, 0.0, 60.0, seq), Decision(seq, OBJECT))
        self.router.notify(PLAN_PATH)


class Published:
    """What the controller publishes, awaitable by decision count."""

    def __init__(self) -> None:
        self.decisions: list[Decision] = []
        self._changed = asyncio.Event()

    def __call__(self, state: RobotState) -> None:
        assert state.last is not None
        self.decisions.append(state.last)
        self._changed.set()

    async def wait(self, count: int, timeout: float = 5.0) -> list[Decision]:
        async with asyncio.timeout(timeout):
            while len(self.decisions) < count:  # no await between the check and the wait: no lost wake-up
                self._changed.clear()
                await self._changed.wait()
        return self.decisions


class Harness:
    def __init__(self, controller: Controller, published: Published, sent: list[DecisionMessage]) -> None:
        self.controller, self.published, self.sent = controller, published, sent


@pytest.fixture
async def make(network: MemoryNetwork, all_kbs: KnowledgeBase):
    """``make(config, queries=None)``: a started controller of ``config``'s robot."""
    started: list[tuple[Controller, TeamView, TaskExecutor]] = []

    async def build(cfg: RobotConfig, queries: object = None,
                    send: Callable[[DecisionMessage], Awaitable[None]] | None = None) -> Harness:
        client = network.client()
        own = _state(cfg.robot_id)
        team = TeamView(own, {r: m.endpoint for r, m in cfg.team.items() if r != cfg.robot_id}, client)
        executor = TaskExecutor(cfg.execution, own.live, lambda live: None)
        published = Published()
        sent: list[DecisionMessage] = []

        async def record(message: DecisionMessage) -> None:
            sent.append(message)

        if queries is None:
            kb = all_kbs if cfg.team[cfg.robot_id].kbs else None
            queries = QueryHandler(cfg, kb, KBClient(client))
        controller = Controller(cfg, queries, team, executor, published, send or record)  # type: ignore[arg-type]
        team.start()
        executor.start()
        controller.start()
        started.append((controller, team, executor))
        return Harness(controller, published, sent)

    yield build
    for controller, team, executor in started:
        await controller.aclose()
        await executor.aclose()
        await team.aclose()


async def test_gather_runs_the_four_queries(make: Callable) -> None:
    h = await make(config("Robot1", {"Robot1": ALL, "Robot2": (), "Robot4": ()}))
    facts = await h.controller.gather(Task(1, OBJECT))
    assert not isinstance(facts, str) and facts.object == OBJECT and facts.weight_kg > 0
    assert set(facts.capable) <= {"Robot1", "Robot2", "Robot4"} and facts.capable  # only teammates
    assert await h.controller.gather(Task(2, "Nonexistent_widget_1")) == "no such object"


async def test_an_object_without_a_place_is_said_to_lack_its_place_not_its_features(
    make: Callable, network: MemoryNetwork, all_kbs: KnowledgeBase
) -> None:
    """A new product written into the Object KB alone: its grip and weight
    are there, its shelf is not."""
    cfg = config("Robot1", {"Robot1": ALL, "Robot2": (), "Robot4": ()})
    real = QueryHandler(cfg, all_kbs, KBClient(network.client()))

    class NoPlace:
        wire = real.wire

        async def run(self, name: str, params: Mapping[str, str], *, at: int | None = None) -> object:
            if name == "pick-place":
                return SelectResult(("aisle_no", "rack_no", "bin_no", "picked_by", "picked_task", "missing_task"), ())
            return await real.run(name, params, at=at)

        def __getattr__(self, name: str) -> object:
            return getattr(real, name)

    h = await make(cfg, queries=NoPlace())
    with pytest.raises(QueryError) as raised:
        await h.controller.gather(Task(1, OBJECT))
    assert str(raised.value) == f"{OBJECT} exists but has no place (aisle, rack, bin) in the Location KB"


async def test_compute_by_all_waits_for_every_teammate_to_decide_the_previous_task(
    make: Callable, network: MemoryNetwork
) -> None:
    mate = Teammate("Robot2")
    await network.serve(mate.router, endpoint("Robot2"))
    h = await make(config("Robot1", PAIR))
    h.controller.submit(Task(1, OBJECT))
    h.controller.submit(Task(2, OTHER_OBJECT))
    first = (await h.published.wait(1))[0]
    assert first.seq == 1 and first.error is None and first.assigned_to in ("Robot1", "Robot2")
    assert set(first.costs) == {"Robot1", "Robot2"}
    # Task 2 needs Robot2's state after task 1: nothing is decided until it publishes it.
    with pytest.raises(TimeoutError):
        await h.published.wait(2, timeout=0.3)
    mate.decide(1)
    second = (await h.published.wait(2))[1]
    assert second.seq == 2 and second.error is None and set(second.costs) == {"Robot1", "Robot2"}
    assert h.sent == []  # compute-by-all sends nothing
    assert h.controller.team.own.plan.seq == 2


async def test_the_winner_gets_the_job_and_plans_ahead(make: Callable) -> None:
    h = await make(config("Robot1", {"Robot1": ALL}))
    h.controller.submit(Task(1, OBJECT))
    decision = (await h.published.wait(1))[0]
    assert decision.assigned_to == "Robot1"
    await asyncio.wait_for(h.controller.executor.wait_idle(), 5)
    assert h.controller.executor.live.done == 1
    plan = h.controller.team.own.plan
    assert plan.seq == 1 and plan.battery_wh < 400.0


async def test_compute_and_communicate_leader_sends_its_decision(make: Callable) -> None:
    h = await make(config("Robot1", {"Robot1": ALL}, strategy="compute-and-communicate"))
    h.controller.submit(Task(1, "Nonexistent_widget_1"))
    await h.published.wait(1)
    assert [m.decision.skipped for m in h.sent] == [True]


async def test_a_failed_send_leaves_the_leaders_decision_standing(make: Callable) -> None:
    async def unreachable(message: DecisionMessage) -> None:
        raise TransportError("decision not delivered to Robot2")

    h = await make(config("Robot1", {"Robot1": ALL}, strategy="compute-and-communicate"), send=unreachable)
    h.controller.submit(Task(1, "Nonexistent_widget_1"))
    assert (await h.published.wait(1))[0].error is None


async def test_compute_and_communicate_follower_applies_the_leaders_decision(make: Callable) -> None:
    h = await make(config("Robot2", PAIR, strategy="compute-and-communicate"), queries=NoQueries())
    h.controller.submit(Task(1, OBJECT))
    h.controller.receive_decision(DecisionMessage(Decision(1, OBJECT, assigned_to="Robot1", costs={"Robot1": 1.5})))
    decision = (await h.published.wait(1))[0]
    assert (decision.assigned_to, decision.costs, decision.error) == ("Robot1", {"Robot1": 1.5}, None)
    assert h.controller.team.own.plan.seq == 1 and h.controller.executor.live.queued == 0


async def test_a_follower_without_the_leaders_decision_records_an_error(make: Callable) -> None:
    h = await make(config("Robot2", PAIR, strategy="compute-and-communicate", query_timeout_s=0.02),
                   queries=NoQueries())
    h.controller.submit(Task(1, OBJECT))
    assert (await h.published.wait(1))[0].error == "no decision from Robot1 for task 1"


class NoQueries:
    """A Query Handler that must not be asked."""

    wire = "compact"

    def begin(self, task: int) -> None:
        pass

    async def run(self, name: str, params: Mapping[str, str], *, at: int | None = None) -> object:
        raise AssertionError(f"unexpected query {name}")


class Failing:
    wire = "compact"

    def begin(self, task: int) -> None:
        pass

    def __init__(self, error: Exception) -> None:
        self.error = error

    async def run(self, name: str, params: Mapping[str, str], *, at: int | None = None) -> object:
        raise self.error


@pytest.mark.parametrize("error, expected", [
    (QueryError("pick-facts to Robot2 failed: 5.03"), "pick-facts to Robot2 failed: 5.03"),
    (TransportError("no state for task 0 from Robot2"), "no state for task 0 from Robot2"),
    (RuntimeError("a bug"), "internal error: a bug"),
])
async def test_failures_become_the_decisions_error_and_the_robot_goes_on(
    make: Callable, error: Exception, expected: str
) -> None:
    h = await make(config("Robot1", {"Robot1": ALL}), queries=Failing(error))
    h.controller.submit(Task(1, OBJECT))
    h.controller.submit(Task(2, OBJECT))
    decisions = await h.published.wait(2)
    assert [(d.seq, d.error, d.assigned_to) for d in decisions] == [(1, expected, None), (2, expected, None)]


class UpMembership:
    """A membership of ``members`` that never changes, with a majority up."""

    def __init__(self, members: tuple[str, ...]) -> None:
        self.members = members
        self.epoch = 0
        self.alone = False

    def adopt(self, membership: Membership, seq: int) -> None:
        pass


class UpTeam:
    """What :meth:`Controller._settle` reads of the team: everyone up, a
    majority; failures recorded and not counted."""

    def __init__(self, robot_id: str, members: tuple[str, ...]) -> None:
        self.membership = UpMembership(members)
        self.robot_id = robot_id

    def is_up(self, robot_id: str) -> bool:
        return True

    async def request_failed(self, robot_id: str, exc: Exception) -> None:
        pass


@pytest.mark.looptime  # the frozen ask and the deadline on the event loop's own clock: exact on a busy machine
async def test_a_teammate_up_whose_answer_did_not_come_is_asked_again_past_the_deadline() -> None:
    """Robot2 and Robot3 found no holder of a module (Robot1, frozen) and
    settle the task.  Robot2's ask to Robot1 runs out past the deadline;
    Robot1, back, has meanwhile decided on its own knowledge.  Robot1 is
    up, so Robot2 asks it again rather than deciding alone (simulator seeds
    1076, 1453, 1534 and 1535 of the 3-robot swarm profile with writes: one
    robot decided nobody, its teammates Robot1)."""
    cfg = config("Robot2", query_timeout_s=1.0)  # a wait of 2 s, 6 s for one still deciding
    theirs = DecisionMessage(Decision(7, OBJECT, assigned_to="Robot1", epoch=0,
                                      members=("Robot1", "Robot2", "Robot3")))
    alone = DecisionMessage(Decision(7, OBJECT, unavailable="no live robot holds the Location KB"))
    asked: list[str] = []

    async def ask(mate: str, seq: int) -> DecisionMessage | None:
        asked.append(mate)
        if mate == "Robot3":
            return alone  # it failed too
        if asked.count("Robot1") == 1:
            await asyncio.sleep(2.5)  # frozen: past the deadline (two query timeouts)
            raise PeerTimeout("coap://robot1:5683: no answer")
        return theirs

    controller = Controller(cfg, NoQueries(), UpTeam("Robot2", ("Robot1", "Robot2", "Robot3")),  # type: ignore[arg-type]
                            TaskExecutor(cfg.execution, LiveState(0.0, 0.0), lambda live: None), lambda state: None, None,
                            ask_decision=ask)  # type: ignore[arg-type]
    async with asyncio.timeout(10):
        settled = await controller.settler.settle(Task(7, OBJECT), alone)
    assert settled is theirs and asked.count("Robot1") == 2


class FailingTeam(UpTeam):
    """A team whose teammates are declared down at their second failed request."""

    def __init__(self, robot_id: str, members: tuple[str, ...], down: set[str]) -> None:
        super().__init__(robot_id, members)
        self.down = down
        self.failures: dict[str, int] = {}
        self.revival = self  # a teammate heard again is up again

    async def heard_again(self, robot_id: str) -> bool:
        self.down.discard(robot_id)
        return True

    def is_up(self, robot_id: str) -> bool:
        return robot_id not in self.down

    async def request_failed(self, robot_id: str, exc: Exception) -> None:
        self.failures[robot_id] = self.failures.get(robot_id, 0) + 1
        if self.failures[robot_id] >= 2:
            self.down.add(robot_id)
        up = [r for r in self.membership.members if r == self.robot_id or r not in self.down]
        self.membership.alone = len(up) * 2 <= len(self.membership.members)


@pytest.mark.looptime  # the silence and the waits on the event loop's own clock
async def test_a_robot_outnumbered_by_the_failure_of_the_round_waits_for_the_silent_teammate() -> None:
    """Robot2 did not get its knowledge (Robot1, the holder, is dead) and
    settles the task; Robot3 decided on knowledge and was cut off.  Robot3
    is found down in a round that asks it: Robot2 is then outnumbered, and
    a silence is no answer, so it waits on and takes Robot3's decision
    once it answers (simulator seed 54708 of the storage profile: it
    counted Robot3 as failed and decided the task alone, for nobody)."""
    theirs = DecisionMessage(Decision(1, OBJECT, assigned_to="Robot2", epoch=0,
                                      members=("Robot1", "Robot2", "Robot3")))
    alone = DecisionMessage(Decision(1, OBJECT, unavailable="no live robot holds the Location KB"))
    team = FailingTeam("Robot2", ("Robot1", "Robot2", "Robot3"), down={"Robot1"})
    loop = asyncio.get_running_loop()
    healed_at = loop.time() + 4.5  # past the wait's first deadline (two query timeouts)

    async def ask(mate: str, seq: int) -> DecisionMessage | None:
        if mate == "Robot1":
            raise PeerGone("coap://robot1:5683: port unreachable")
        if loop.time() < healed_at:
            await asyncio.sleep(1.0)
            raise PeerTimeout("coap://robot3:5683: no answer")
        return theirs

    settler = Settler("Robot2", team, 1.0, ask, {})  # type: ignore[arg-type]
    async with asyncio.timeout(10):
        settled = await settler.settle(Task(1, OBJECT), alone)
    assert team.failures["Robot3"] >= 2 and settled is theirs  # found down, then heard again


class StalledTeam(UpTeam):
    """A team seen by a robot whose loop just stood still for 20 s."""

    request_timeout_s = 1.0

    def stalled_within(self, window_s: float) -> float:
        return 20.0

    def state_of(self, robot_id: str) -> RobotState | None:
        return None


def _stalled_settler(ask: Callable[[str, int], Awaitable[DecisionMessage | None]],
                     fenced: str | None) -> Settler:
    async def lease() -> str | None:
        return fenced

    team = StalledTeam("Robot1", ("Robot1", "Robot2", "Robot3"))
    return Settler("Robot1", team, 1.0, ask, {}, fenced=lease)  # type: ignore[arg-type]


@pytest.mark.looptime  # the polls on the event loop's own clock
async def test_a_fenced_robot_back_from_a_stall_waits_for_its_teammates_decision() -> None:
    """Robot1, back from a freeze, finds Robot2 and Robot3 still deciding
    the task and no majority granting it a lease: they have it down and
    will not take its decision, so it takes theirs once they apply it
    (simulator seed 43737: it decided on its own knowledge, they settled
    the task unavailable)."""
    settled = DecisionMessage(Decision(3, OBJECT, unavailable="no live robot holds the Location KB", epoch=0,
                                       members=("Robot1", "Robot2", "Robot3")))
    settling = DecisionMessage(Decision(3, OBJECT, unavailable="no live robot holds the Location KB"))
    asked: list[str] = []

    async def ask(mate: str, seq: int) -> DecisionMessage | None:
        asked.append(mate)
        if len(asked) < 6:
            return None if mate == "Robot2" else settling  # deciding again; settling, not applied
        return settled

    settler = _stalled_settler(ask, fenced="no lease from a majority of the cluster")
    taken = await settler.decided_before(Task(3, OBJECT), received=0.0)
    assert taken is settled and len(asked) >= 6


@pytest.mark.looptime
async def test_a_robot_back_from_a_stall_still_granted_decides_on_its_own_knowledge() -> None:
    """Teammates that still grant it count it: as they settle they take its
    decision on knowledge, so it does not wait for theirs."""
    asked: list[str] = []

    async def ask(mate: str, seq: int) -> DecisionMessage | None:
        asked.append(mate)
        return None

    assert await _stalled_settler(ask, fenced=None).decided_before(Task(3, OBJECT), received=0.0) is None
    assert sorted(asked) == ["Robot2", "Robot3"]


@pytest.mark.looptime
async def test_a_fenced_robot_left_out_stops_waiting_at_once() -> None:
    """Teammates that decided in a membership without it never give it a
    decision to take; its own is void, so it stops waiting."""
    without = DecisionMessage(Decision(4, OBJECT, assigned_to="Robot2", epoch=1, members=("Robot2", "Robot3")))
    asked: list[str] = []

    async def ask(mate: str, seq: int) -> DecisionMessage | None:
        asked.append(mate)
        return without

    loop = asyncio.get_running_loop()
    began = loop.time()
    assert await _stalled_settler(ask, fenced="refused").decided_before(Task(4, OBJECT), received=0.0) is None
    assert loop.time() - began < 1.0 and len(asked) == 4


@pytest.mark.looptime
async def test_a_fenced_robot_stops_waiting_for_a_teammate_past_the_task_without_its_decision() -> None:
    """A teammate whose plan is past the task and answers that it has no
    decision on it no longer keeps one: none will come."""
    class PastTeam(StalledTeam):
        def state_of(self, robot_id: str) -> RobotState | None:
            return _state(robot_id, seq=80)

    async def ask(mate: str, seq: int) -> DecisionMessage | None:
        return None

    async def lease() -> str | None:
        return "refused"

    settler = Settler("Robot1", PastTeam("Robot1", ("Robot1", "Robot2", "Robot3")), 1.0, ask, {},  # type: ignore[arg-type]
                      fenced=lease)
    loop = asyncio.get_running_loop()
    began = loop.time()
    assert await settler.decided_before(Task(4, OBJECT), received=0.0) is None
    assert loop.time() - began < 1.0
