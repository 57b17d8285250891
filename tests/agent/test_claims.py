"""The cluster's claims (Controller.claims, a ClusterClaims): an object the cluster already
gave to a robot is skipped without a query, "picked by R at task S", alike
on every robot; a task done again frees its object; a restarted robot takes
the claims of the tasks before it from a teammate; and ``/robot/claims``'s
CBOR (encode_claims/decode_claims).  Teammates are routers on the in-memory
transport; no processes."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping

import cbor2
import pytest
from agent_helpers import config, endpoint

from coapkb.agent.controller import DEFAULT_BOUNDS, Controller, RobotBounds
from coapkb.agent.decisions import Claim, DecisionMessage, Task, decode_claims, encode_claims
from coapkb.agent.observed_states import PLAN_PATH, STATE_PATH
from coapkb.agent.query_handler import QueryHandler
from coapkb.agent.robot_state import Decision, LiveState, PlannedState, RobotState
from coapkb.agent.task_executor import TaskExecutor
from coapkb.agent.team_view import TeamView
from coapkb.config import RobotConfig
from coapkb.kb.client import KBClient
from coapkb.kb.store import KnowledgeBase
from coapkb.transport.base import ResourceInfo, TransportError
from coapkb.transport.memory import MemoryNetwork
from coapkb.transport.messages import ContentFormat, Request, Response, Status
from coapkb.transport.router import Router

ALL = ("Location", "Object", "Capability")
ALONE = {"Robot1": ALL}
BAG, TV, PASTA = "Gucci_bag_14", "Canon_tv_538", "Barilla_pasta_1"


# ------------------------------------------------------------------ the wire


def test_claims_round_trip_through_their_cbor() -> None:
    claims = {BAG: Claim("Robot2", 1), TV: Claim("Robot1", 2), PASTA: Claim("Robot10", 2**40)}
    data = encode_claims(claims)
    assert cbor2.loads(data) == [[BAG, "Robot2", 1], [TV, "Robot1", 2], [PASTA, "Robot10", 2**40]]
    assert decode_claims(data) == claims and list(decode_claims(data)) == list(claims)
    assert decode_claims(encode_claims({})) == {}
    assert str(Claim("Robot2", 1)) == "picked by Robot2 at task 1"


GARBAGE = {
    "empty": b"",
    "not-cbor": b"\xff\xff",
    "cut-short": b"\x82\x83\x61a",
    "a-map": cbor2.dumps({BAG: ["Robot2", 1]}),
    "a-text": cbor2.dumps("claims"),
    "a-claim-of-two": cbor2.dumps([[BAG, "Robot2"]]),
    "a-claim-of-four": cbor2.dumps([[BAG, "Robot2", 1, 2]]),
    "a-claim-not-an-array": cbor2.dumps([BAG]),
    "seq-zero": cbor2.dumps([[BAG, "Robot2", 0]]),
    "seq-negative": cbor2.dumps([[BAG, "Robot2", -3]]),
    "seq-bool": cbor2.dumps([[BAG, "Robot2", True]]),
    "seq-text": cbor2.dumps([[BAG, "Robot2", "1"]]),
    "seq-float": cbor2.dumps([[BAG, "Robot2", 1.0]]),
    "robot-null": cbor2.dumps([[BAG, None, 1]]),
    "object-bytes": cbor2.dumps([[BAG.encode(), "Robot2", 1]]),
    "one-bad-among-good": cbor2.dumps([[BAG, "Robot2", 1], [TV, "Robot1", "x"]]),
    "deep-nesting": b"\x81" * 5000 + b"\x00",
}


@pytest.mark.parametrize("data", GARBAGE.values(), ids=GARBAGE.keys())
def test_anything_but_claims_is_a_value_error(data: bytes) -> None:
    with pytest.raises(ValueError):
        decode_claims(data)


# ---------------------------------------------------------------- the controller


class Published:
    """What the controller publishes, awaitable by decision count."""

    def __init__(self) -> None:
        self.decisions: list[Decision] = []
        self._changed = asyncio.Event()

    def __call__(self, state: RobotState) -> None:
        if state.last is None:  # a restarted robot's plan as it joins: no decision yet
            return
        self.decisions.append(state.last)
        self._changed.set()

    async def wait(self, count: int, timeout: float = 5.0) -> list[Decision]:
        async with asyncio.timeout(timeout):
            while len(self.decisions) < count:  # no await between the check and the wait
                self._changed.clear()
                await self._changed.wait()
        return self.decisions


class Counting:
    """A Query Handler that counts the questions about each object."""

    def __init__(self, inner: QueryHandler) -> None:
        self.inner = inner
        self.wire = inner.wire
        self.asked: dict[str, int] = {}

    def begin(self, task: int) -> None:
        self.inner.begin(task)

    async def run(self, name: str, params: Mapping[str, str], *, at: int | None = None) -> object:
        if "name" in params:
            self.asked[params["name"]] = self.asked.get(params["name"], 0) + 1
        return await self.inner.run(name, params, at=at)


class Harness:
    def __init__(self, controller: Controller, published: Published, queries: Counting) -> None:
        self.controller, self.published, self.queries = controller, published, queries


def _state(robot_id: str, seq: int = 0) -> RobotState:
    return RobotState(robot_id, PlannedState(1, 0, 400.0, 0.0, 60.0, seq), LiveState(1.0, 0.0))


@pytest.fixture
async def make(network: MemoryNetwork, all_kbs: KnowledgeBase) -> AsyncIterator[Callable]:
    """``make(config, ask_claims=None)``: a started controller of ``config``'s robot."""
    started: list[tuple[Controller, TeamView, TaskExecutor]] = []

    async def build(cfg: RobotConfig, ask_claims: Callable[[str], Awaitable[dict[str, Claim]]] | None = None,
                    bounds: RobotBounds = DEFAULT_BOUNDS) -> Harness:
        client = network.client()
        team = TeamView(_state(cfg.robot_id), {r: m.endpoint for r, m in cfg.team.items() if r != cfg.robot_id},
                        client)
        executor = TaskExecutor(cfg.execution, team.own.live, lambda live: None)
        published = Published()
        queries = Counting(QueryHandler(cfg, all_kbs, KBClient(client)))

        async def send(message: DecisionMessage) -> None:
            pass

        controller = Controller(cfg, queries, team, executor, published, send,  # type: ignore[arg-type]
                                ask_claims=ask_claims, bounds=bounds)
        team.start()
        executor.start()
        controller.start()
        started.append((controller, team, executor))
        return Harness(controller, published, queries)

    yield build
    for controller, team, executor in started:
        await controller.aclose()
        await executor.aclose()
        await team.aclose()


async def test_a_repeated_object_is_skipped_as_picked_without_a_query(make: Callable) -> None:
    h = await make(config("Robot1", ALONE))
    for seq, obj in enumerate((BAG, TV, BAG, TV), start=1):
        h.controller.submit(Task(seq, obj))
    decisions = await h.published.wait(4)
    assert [(d.seq, d.assigned_to, d.skipped, d.skip_reason) for d in decisions] == [
        (1, "Robot1", False, None), (2, "Robot1", False, None),
        (3, None, True, "picked by Robot1 at task 1"), (4, None, True, "picked by Robot1 at task 2")]
    # pick-facts and pick-place once each, for the first task of each object only.
    assert h.queries.asked == {BAG: 2, TV: 2}
    assert h.controller.claims == {BAG: Claim("Robot1", 1), TV: Claim("Robot1", 2)}
    assert [t.seq for t in h.controller.log] == [1, 2, 3, 4]


async def test_only_an_assignment_is_a_claim(make: Callable) -> None:
    h = await make(config("Robot1", ALONE))
    h.controller.submit(Task(1, "Nonexistent_widget_1"))
    h.controller.submit(Task(2, "Nonexistent_widget_1"))
    decisions = await h.published.wait(2)
    assert [d.skip_reason for d in decisions] == ["no such object", "no such object"]
    assert h.controller.claims == {}


async def test_a_task_done_again_frees_its_object(make: Callable) -> None:
    """Task 3 does task 1 again (its robot went down before the pick): not
    "picked by ... at task 1", and the claim moves to task 3."""
    h = await make(config("Robot1", ALONE))
    h.controller.submit(Task(1, BAG))
    h.controller.submit(Task(2, TV))
    h.controller.submit(Task(3, BAG, again=1))
    h.controller.submit(Task(4, BAG))
    decisions = await h.published.wait(4)
    assert [(d.seq, d.assigned_to, d.skip_reason) for d in decisions] == [
        (1, "Robot1", None), (2, "Robot1", None), (3, "Robot1", None), (4, None, "picked by Robot1 at task 3")]
    assert h.controller.claims == {TV: Claim("Robot1", 2), BAG: Claim("Robot1", 3)}
    assert list(h.controller.claims) == [TV, BAG]  # the latest last


async def test_claims_are_bounded_and_a_teammate_is_handed_the_latest(
    make: Callable,
) -> None:
    h = await make(config("Robot1", ALONE), bounds=RobotBounds(claims_kept=2, claims_handed=1))
    for seq, obj in enumerate((BAG, TV, PASTA), start=1):
        h.controller.submit(Task(seq, obj))
    await h.published.wait(3)
    assert h.controller.claims == {TV: Claim("Robot1", 2), PASTA: Claim("Robot1", 3)}
    assert h.controller.claims.handed() == {PASTA: Claim("Robot1", 3)}
    assert decode_claims(encode_claims(h.controller.claims.handed())) == {PASTA: Claim("Robot1", 3)}


class Teammate:
    """A live teammate that decided task ``seq`` among ``members`` (its
    /robot/state and /robot/plan), as a restarted robot finds it."""

    def __init__(self, robot_id: str, seq: int, members: tuple[str, ...]) -> None:
        self.state = _state(robot_id, seq).with_plan(PlannedState(1, 0, 400.0, 0.0, 60.0, seq),
                                                     Decision(seq, PASTA, epoch=1, members=members))
        self.router = Router()
        self.router.add(ResourceInfo(STATE_PATH, obs=True), self._get_state)
        self.router.add(ResourceInfo(PLAN_PATH, obs=True), self._get_plan)

    async def _get_state(self, request: Request) -> Response:
        return Response(Status.CONTENT, self.state.encode(), ContentFormat.CBOR)

    async def _get_plan(self, request: Request) -> Response:
        return Response(Status.CONTENT, self.state.encode_plan(), ContentFormat.CBOR)


async def test_a_restarted_robot_takes_the_claims_of_the_tasks_before_it(
    make: Callable, network: MemoryNetwork
) -> None:
    """Robot1 joins at task 5.  Robot2 hands it claims up to task 5 (it may have
    decided task 5 already): task 5's own is not one of the tasks before."""
    mate = Teammate("Robot2", 4, ("Robot2",))
    await network.serve(mate.router, endpoint("Robot2"))
    asked: list[str] = []

    async def ask_claims(robot_id: str) -> dict[str, Claim]:
        asked.append(robot_id)
        return {BAG: Claim("Robot2", 2), PASTA: Claim("Robot2", 1), TV: Claim("Robot2", 5)}

    h = await make(config("Robot1", {"Robot1": ALL, "Robot2": ()}), ask_claims=ask_claims)
    h.controller.submit(Task(5, TV, join=("Robot1",)))
    h.controller.submit(Task(6, BAG))
    decisions = await h.published.wait(2)
    assert asked == ["Robot2"]
    five, six = decisions
    assert not five.skipped and five.assigned_to in ("Robot1", "Robot2"), five
    assert (six.skipped, six.skip_reason) == (True, "picked by Robot2 at task 2")
    assert h.controller.claims[PASTA] == Claim("Robot2", 1)
    assert h.controller.claims[TV] == Claim(five.assigned_to, 5)


async def test_a_teammate_that_cannot_hand_its_claims_over_is_passed_by(
    make: Callable, network: MemoryNetwork
) -> None:
    for robot_id in ("Robot2", "Robot3"):
        mate = Teammate(robot_id, 4, ("Robot2", "Robot3"))
        await network.serve(mate.router, endpoint(robot_id))
    asked: list[str] = []

    async def ask_claims(robot_id: str) -> dict[str, Claim]:
        asked.append(robot_id)
        if robot_id == "Robot2":
            raise TransportError("Robot2's claims: not CBOR")
        return {BAG: Claim("Robot3", 3)}

    h = await make(config("Robot1", {"Robot1": ALL, "Robot2": (), "Robot3": ()}), ask_claims=ask_claims)
    h.controller.submit(Task(5, BAG, join=("Robot1",)))
    [decision] = await h.published.wait(1)
    assert asked == ["Robot2", "Robot3"]  # in robot-id order, the first that answers
    assert (decision.skipped, decision.skip_reason) == (True, "picked by Robot3 at task 3")
