"""Comparing notes on a teammate's plan (``POST /robot/plan?of=X&at=S``):
the robot asked goes on without X's plan if it has none, but only when a
member of its own membership asks."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any, cast

from coapkb.agent.robot_resources import RobotResources
from coapkb.agent.robot_state import LiveState, PlannedState, RobotState
from coapkb.agent.team_membership import Membership
from coapkb.agent.team_view import TeamView
from coapkb.transport.base import Endpoint
from coapkb.transport.memory import MemoryNetwork
from coapkb.transport.messages import Method, Request, Response, Status


def _robot1(transport: Any = None) -> tuple[TeamView, RobotResources]:
    own = RobotState("Robot1", PlannedState(1, 0, 400.0, 0.0, 40.0, seq=6), LiveState(1.0, 0.0))
    mates = {"Robot2": Endpoint("coap", "127.0.0.1", 2), "Robot3": Endpoint("coap", "127.0.0.1", 3)}
    team = TeamView(own, mates, transport)
    resources = RobotResources(cast(Any, SimpleNamespace(robot_id="Robot1")), team,
                               cast(Any, None), cast(Any, None), cast(Any, None))
    return team, resources


async def _ask(resources: RobotResources, query: dict[str, str], peer: str | None = None) -> Response:
    return await resources._plan(Request(Method.POST, "/robot/plan", query, peer=peer))


async def test_a_member_without_the_plan_binds_the_robot_asked_to_go_on_without_it() -> None:
    team, resources = _robot1()
    answer = await _ask(resources, {"of": "Robot3", "at": "5", "by": "Robot2"})
    assert answer.status == Status.NOT_FOUND and team.membership.forgoes("Robot3", 5)


async def test_a_robot_left_out_asks_but_binds_nothing() -> None:
    """Robot1 left Robot2 out: Robot2 decides in a membership of its own, and
    a question of it must not make Robot1 leave Robot3 out alone (simulator,
    three robots, seed 90301: the majority split in two)."""
    team, resources = _robot1()
    team.membership.leave_out("Robot2", 3, "cut off")
    by_query = await _ask(resources, {"of": "Robot3", "at": "5", "by": "Robot2"})
    secured = await _ask(resources, {"of": "Robot3", "at": "5"}, peer="Robot2")
    assert by_query.status == secured.status == Status.NOT_FOUND
    assert not team.membership.forgoes("Robot3", 5)


async def test_an_asker_outside_the_cluster_is_refused() -> None:
    team, resources = _robot1()
    for answer in (await _ask(resources, {"of": "Robot3", "at": "5", "by": "Robot9"}),
                   await _ask(resources, {"of": "Robot3", "at": "5"}, peer="Robot9")):
        assert answer.status == Status.FORBIDDEN and "Robot9" in answer.text()
    assert not team.membership.forgoes("Robot3", 5)


async def test_a_question_from_before_a_teammates_join_binds_nothing() -> None:
    """Robot3 restarted and joined at task 6, showing its plan after task 5;
    a try of Robot2's question about its plan after task 4, held back on the
    way, arrives now: about the process that left, it must not make Robot1
    leave the new one out (simulator, three robots, late messages, seed
    686: Robot1 alone left Robot3 out from task 7 on, one epoch ahead)."""
    team, resources = _robot1(MemoryNetwork().client())  # the admission observes Robot3 again
    try:
        team.membership.leave_out("Robot3", 4, "restarted")
        team.membership.admit("Robot3", 6)
        late = await _ask(resources, {"of": "Robot3", "at": "4", "by": "Robot2"})
        assert late.status == Status.NOT_FOUND
        assert not team.membership.forgoes("Robot3", 6) and not team.membership.left_out("Robot3")
        # A question about the new process's first plan binds as any other.
        await _ask(resources, {"of": "Robot3", "at": "5", "by": "Robot2"})
        assert team.membership.forgoes("Robot3", 5)
    finally:
        await team.aclose()


async def test_once_without_the_plan_every_later_try_is_answered_without_it() -> None:
    """Robot2 asks twice (a try lost, or held back); the first try found
    Robot1 without Robot3's plan after task 5, and the plan arrived before
    the second: the second is answered 4.04 as well, else Robot2 would count
    Robot3 in where Robot1 promised to leave it out (simulator, seed 1308)."""
    team, resources = _robot1()
    first = await _ask(resources, {"of": "Robot3", "at": "5", "by": "Robot2"})
    team._teammates.states["Robot3"] = RobotState("Robot3", PlannedState(3, 0, 400.0, 0.0, 40.0, seq=5),
                                                  LiveState(1.0, 0.0))
    second = await _ask(resources, {"of": "Robot3", "at": "5", "by": "Robot2"})
    assert first.status == second.status == Status.NOT_FOUND


async def test_once_shown_the_plan_every_later_try_is_shown_it_again() -> None:
    """Robot2 asks for Robot3's plan after task 5 and is shown it; a try of
    the same question, held back past the next tasks, arrives when Robot1
    holds only Robot3's later plans.  It is shown the same plan, and binds
    Robot1 to nothing: answered without it, Robot1 left Robot3 out, while
    Robot2 counted it in (simulator, seed 4608 of three robots with
    messages held back and hedged retries)."""
    team, resources = _robot1()
    team._teammates.states["Robot3"] = RobotState("Robot3", PlannedState(3, 0, 400.0, 0.0, 40.0, seq=5),
                                                  LiveState(1.0, 0.0))
    first = await _ask(resources, {"of": "Robot3", "at": "5", "by": "Robot2"})
    team._teammates.states["Robot3"] = RobotState("Robot3", PlannedState(4, 0, 390.0, 0.0, 40.0, seq=7),
                                                  LiveState(1.0, 0.0))
    late = await _ask(resources, {"of": "Robot3", "at": "5", "by": "Robot2"})
    assert first.status == late.status == Status.CHANGED and late.payload == first.payload
    assert not team.membership.forgoes("Robot3", 5)
    # A question about a plan never shown binds as before.
    assert (await _ask(resources, {"of": "Robot3", "at": "6", "by": "Robot2"})).status == Status.NOT_FOUND
    assert team.membership.forgoes("Robot3", 6)


async def test_a_robot_fed_again_drops_its_promises_about_the_members_it_joins() -> None:
    """Robot1 promised at its first task to go on without Robot3's plans, was
    cut off and left out; meanwhile Robot2 took Robot3 back.  Fed again at
    task 13, Robot1 takes the membership of task 12, Robot3 a member: the
    promise, made while it was out, must not leave Robot3 out again at its
    first task (simulator, nine robots, seed 53530: an epoch of its own)."""
    team, resources = _robot1()
    await _ask(resources, {"of": "Robot3", "at": "0", "by": "Robot2"})
    assert team.membership.forgoes("Robot3", 12)
    team.membership._joined(13, Membership(3, ("Robot2", "Robot3")))
    assert not team.membership.forgoes("Robot3", 12) and team.membership.counts("Robot3") is None
