"""ObservedStates recovers from an observation the server dropped silently."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from dataclasses import replace

import pytest

from coapkb.agent.observed_states import PLAN_PATH, ObservedStates
from coapkb.agent.robot_state import LiveState, PlannedState, RobotState
from coapkb.transport.base import Endpoint, PeerTimeout, TrafficCounters, TransportError
from coapkb.transport.messages import ContentFormat, Request, Response, Status


def state(seq: int) -> RobotState:
    return RobotState("Robot2", PlannedState(1, 0, 400.0, 0.0, 30.0, seq), LiveState(1.0, 0.0))


class SilentlyDroppedObservation:
    """Observe yields the first state, then nothing (the server dropped the
    observation); a plain GET already sees the robot's newer state."""

    def __init__(self) -> None:
        self.counters = TrafficCounters()
        self.current = state(0)
        self.observations = 0

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        return Response(Status.CONTENT, self.current.encode_plan(), ContentFormat.CBOR)

    async def observe(self, peer: Endpoint, request: Request) -> AsyncIterator[Response]:
        self.observations += 1
        yield Response(Status.CONTENT, self.current.encode_plan(), ContentFormat.CBOR)
        await asyncio.Event().wait()  # no notification ever again

    async def aclose(self) -> None:
        pass


async def test_a_stale_observation_is_refreshed_and_registered_again() -> None:
    transport = SilentlyDroppedObservation()
    states = ObservedStates(transport, {"Robot2": Endpoint("coap", "127.0.0.1", 1)}, PLAN_PATH, refresh_s=0.1)
    states.start()
    try:
        await states.wait(lambda s: "Robot2" in s, timeout=2)
        transport.current = state(1)  # decided task 1; the notification never comes
        seen = await states.wait(lambda s: s["Robot2"].plan.seq >= 1, timeout=2)
        assert seen["Robot2"].plan.seq == 1
        assert states.refreshes >= 1
        await asyncio.sleep(0)  # let the new watcher register
        assert transport.observations == 2
    finally:
        await states.aclose()


async def test_a_lost_notification_is_asked_for_once_late_and_the_observation_stays() -> None:
    """A NON notification lost: the wait GETs the robot's state after
    ``repair_s`` (not after the refresh period), without registering again;
    a state that came unasked is a lateness sample."""
    transport = SilentlyDroppedObservation()
    states = ObservedStates(transport, {"Robot2": Endpoint("coap", "127.0.0.1", 1)}, PLAN_PATH, refresh_s=60)
    states.start()
    try:
        await states.wait(lambda s: "Robot2" in s, timeout=2)
        transport.current = state(1)  # its notification of task 1 is lost
        seen = await states.wait(lambda s: s["Robot2"].plan.seq >= 1, timeout=2,
                                 pending=lambda s: [] if s["Robot2"].plan.seq >= 1 else ["Robot2"])
        assert seen["Robot2"].plan.seq == 1
        assert (states.repairs, states.refreshes, transport.observations) == (1, 0, 1)
        assert states.lateness.srtt is None  # asked for, so no sample of how late states come
    finally:
        await states.aclose()


class LateNotification(SilentlyDroppedObservation):
    """Notifications come, but later than the first repair: a GET is sent
    first and never answered (lost), then the notification arrives."""

    def __init__(self) -> None:
        super().__init__()
        self.notify = asyncio.Event()
        self.gets = 0

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        self.gets += 1
        self.notify.set()  # the notification overtakes the GET's answer, which never comes
        await asyncio.Event().wait()
        raise AssertionError("unreachable")

    async def observe(self, peer: Endpoint, request: Request) -> AsyncIterator[Response]:
        self.observations += 1
        yield Response(Status.CONTENT, self.current.encode_plan(), ContentFormat.CBOR)
        await self.notify.wait()
        yield Response(Status.CONTENT, self.current.encode_plan(), ContentFormat.CBOR)
        await asyncio.Event().wait()


async def test_a_notification_that_came_after_its_repair_left_is_a_lateness_sample() -> None:
    """As Karn's algorithm keeps a backed-off timer, the estimate must learn
    from states that came unasked even when a GET raced them: otherwise a
    first repair earlier than the links' delay asks for every state forever."""
    transport = LateNotification()
    states = ObservedStates(transport, {"Robot2": Endpoint("coap", "127.0.0.1", 1)}, PLAN_PATH, refresh_s=60)
    states.start()
    try:
        await states.wait(lambda s: "Robot2" in s, timeout=2)
        transport.current = state(1)
        await states.wait(lambda s: s["Robot2"].plan.seq >= 1, timeout=2,
                          pending=lambda s: [] if s["Robot2"].plan.seq >= 1 else ["Robot2"])
        assert transport.gets == 1 and states.repairs == 1
        assert states.lateness.srtt is not None  # the notification's lateness, though a GET had left
    finally:
        await states.aclose()


async def test_awaited_states_are_due_once_the_first_came() -> None:
    """With ``of``, nothing is asked for while every awaited robot is still
    deciding: only once one of them came are the others late."""
    transport = SilentlyDroppedObservation()
    states = ObservedStates(transport, {"Robot2": Endpoint("coap", "127.0.0.1", 1)}, PLAN_PATH, refresh_s=60)
    states.start()
    try:
        await states.wait(lambda s: "Robot2" in s, timeout=2)
        transport.current = state(1)
        with pytest.raises(TimeoutError):  # Robot3 never came: Robot2 is never due
            await states.wait(lambda s: s["Robot2"].plan.seq >= 1, timeout=0.5,
                              pending=lambda s: ["Robot2", "Robot3"], of=2)
        assert states.repairs == 0
    finally:
        await states.aclose()


# --------------------------------------------------------------------------- membership

from agent_helpers import endpoint  # noqa: E402

from coapkb.agent.observed_states import liveness_timeout_s  # noqa: E402
from coapkb.agent.team_membership import Membership  # noqa: E402
from coapkb.agent.team_view import TeamView  # noqa: E402
from coapkb.transport.base import ResourceInfo  # noqa: E402
from coapkb.transport.memory import MemoryNetwork  # noqa: E402
from coapkb.transport.router import Router  # noqa: E402
from coapkb.transport.rtt import RttEstimator  # noqa: E402


def robot(robot_id: str, seq: int, boot: int = 1) -> RobotState:
    return RobotState(robot_id, PlannedState(1, seq, 400.0, 0.0, 30.0, seq), LiveState(1.0, 0.0), boot=boot)


async def serve_plan(network: MemoryNetwork, own: RobotState, seen: dict[str, RobotState] | None = None):
    """A teammate's /robot/plan on the memory network, with ``?of=`` answered from ``seen``."""
    router = Router()

    async def plan(request: Request) -> Response:
        about = request.query.get("of")
        shown = own if about is None else (seen or {}).get(about)
        if shown is None:
            return Response.error(Status.NOT_FOUND, f"no state of {about}")
        return Response(Status.CONTENT, shown.encode_plan(), ContentFormat.CBOR)

    router.add(ResourceInfo(PLAN_PATH, obs=True, methods=("GET", "POST")), plan)
    return await network.serve(router, endpoint(own.robot_id))


def view(network: MemoryNetwork, own: RobotState) -> TeamView:
    return TeamView(own, {r: endpoint(r) for r in ("Robot2", "Robot3")}, network.client())


async def test_a_dead_teammate_without_a_plan_is_excluded_in_a_new_epoch() -> None:
    network = MemoryNetwork()
    dead = await serve_plan(network, robot("Robot2", 0))
    await serve_plan(network, robot("Robot3", 1))
    team = view(network, robot("Robot1", 1))
    team.start()
    try:
        await team._teammates.wait(lambda s: "Robot2" in s, timeout=2)
        await dead.aclose()  # dies before deciding task 1
        plans = await team.planned_states(1, timeout=10)
        assert set(plans) == {"Robot1", "Robot3"}
        assert team.membership.excluded == {"Robot2": 2}
        assert (team.membership.epoch, team.membership.members) == (1, ("Robot1", "Robot3"))
        assert not team.is_up("Robot2")
    finally:
        await team.aclose()


async def test_a_dead_teammates_last_plan_comes_from_a_survivor() -> None:
    network = MemoryNetwork()
    dead = await serve_plan(network, robot("Robot2", 0))
    # Robot3 saw Robot2's plan after task 1; Robot1 never did.
    await serve_plan(network, robot("Robot3", 1), seen={"Robot2": robot("Robot2", 1)})
    team = view(network, robot("Robot1", 1))
    team.start()
    try:
        await team._teammates.wait(lambda s: "Robot2" in s, timeout=2)
        await dead.aclose()
        plans = await team.planned_states(1, timeout=10)
        assert plans["Robot2"] == robot("Robot2", 1).plan
        assert team.membership.excluded == {} and team.membership.epoch == 0
    finally:
        await team.aclose()


def test_liveness_timeout_follows_the_round_trip() -> None:
    rtt = RttEstimator()
    assert liveness_timeout_s(rtt, floor_s=1.0) == 2.0  # no sample yet: twice the floor
    for _ in range(20):
        rtt.on_sample(0.002)
    assert liveness_timeout_s(rtt, floor_s=1.0) == 1.0  # loopback: the floor
    for _ in range(50):
        rtt.on_sample(0.8)
    assert 3.2 <= liveness_timeout_s(rtt, floor_s=1.0) < 6  # a slow link: four smoothed round trips and more


async def test_an_older_state_of_the_same_process_is_stale_not_a_restart() -> None:
    """An answer that left before a newer notification and arrived after it
    (reordered, or replayed from the exchange cache for a retransmitted
    request) shows an older plan with the same boot: it is dropped, and the
    teammate stays up.  A new boot number is a restart (simulator seeds 32,
    65 and 76 of the 3-robot mixed profile: a live teammate was declared
    down and its cluster split)."""
    network = MemoryNetwork()
    states = ObservedStates(network.client(), {"Robot2": endpoint("Robot2")}, PLAN_PATH, liveness=True)
    await states.watcher.update("Robot2", robot("Robot2", 7, boot=5))
    await states.watcher.update("Robot2", robot("Robot2", 6, boot=5))
    assert states.states["Robot2"].plan.seq == 7 and not states.down
    await states.watcher.update("Robot2", robot("Robot2", 0, boot=9))
    assert "restarted" in states.down["Robot2"]


async def test_a_first_state_of_another_process_than_the_leaders_is_a_restart() -> None:
    """Never observed, the leader's process is known by the boot its decision
    carried: a first state with another boot is a restart, one with the same
    boot is the leader (simulator seed 1623 of the 6-robot compute-and-
    communicate swarm profile: the follower waited 20 s for a decision the
    new process was never given)."""
    network = MemoryNetwork()
    states = ObservedStates(network.client(), {"Robot2": endpoint("Robot2"), "Robot3": endpoint("Robot3")},
                            PLAN_PATH, liveness=True)
    states.saw_process("Robot2", 5)
    states.saw_process("Robot3", 7)
    await states.watcher.update("Robot2", robot("Robot2", 0, boot=9))
    await states.watcher.update("Robot3", robot("Robot3", 0, boot=7))
    assert "restarted" in states.down["Robot2"] and "Robot3" not in states.down


async def test_a_first_state_earlier_than_a_plan_used_here_is_a_restart() -> None:
    """Robot1 carried out a decision of task 3 computed on Robot2's and
    Robot3's plans after task 2 (taken from a teammate) before it ever
    observed them: a first state of Robot2 at task 0 is a new process, which
    never decided task 2; Robot3's at task 2 is the one used (simulator seed
    50486: a robot starved from the start waited for a restarted teammate's
    plan of a task its new process never had)."""
    team = view(MemoryNetwork(), robot("Robot1", 3))
    try:
        team.used_plans(Decision(3, "Apple", assigned_to="Robot2",
                                 costs={"Robot1": 2.0, "Robot2": 1.0, "Robot3": None}))
        await team._teammates.watcher.update("Robot2", robot("Robot2", 0, boot=9))
        await team._teammates.watcher.update("Robot3", robot("Robot3", 2, boot=7))
        assert "restarted" in team.down["Robot2"] and team.is_up("Robot3")
    finally:
        await team.aclose()


async def test_the_wait_for_plans_outlasts_finding_a_silent_teammate_down() -> None:
    """Robot2 died before Robot1 ever heard from it; Robot3 holds its last
    plan.  However short the wait asked for, Robot1 waits until its failure
    detector finds Robot2 down and takes the plan from Robot3, as Robot3
    decides with it: giving up first, it decided alone (simulator seeds 2,
    50 and 100 of the 3-robot mixed profile)."""
    network = MemoryNetwork()
    await serve_plan(network, robot("Robot3", 1), seen={"Robot2": robot("Robot2", 1)})
    team = view(network, robot("Robot1", 1))
    team.start()
    try:
        plans = await team.planned_states(1, timeout=0.1)
        assert plans["Robot2"] == robot("Robot2", 1).plan and not team.is_up("Robot2")
    finally:
        await team.aclose()


async def test_a_readmitted_robot_has_a_grace_until_heard_from_and_waits_outlast_it() -> None:
    """A readmitted robot's failed requests do not count for a while (its new
    process may need a new security handshake first), so a wait for plans
    lasts past that grace; once the new process is heard from the grace
    ends, and its death is found as anyone's (simulator seeds 2067, 2144,
    3548, 3868, 8344, 9308: killed again soon after a restart, the robot
    was waited for until its teammates decided nothing)."""
    network = MemoryNetwork()
    states = ObservedStates(network.client(), {"Robot2": endpoint("Robot2")}, PLAN_PATH, liveness=True)
    # a refresh, two failed requests and an indirect probe (two request timeouts)
    plain = states.refresh_s + 4 * states.request_timeout_s + 1.0
    try:
        states.readmit("Robot2")
        assert states.detection_s > plain + 1.0
        await states.watcher.update("Robot2", robot("Robot2", 1))
        assert abs(states.detection_s - plain) < 1e-6
    finally:
        await states.aclose()


async def test_a_joiner_named_by_its_process_is_down_when_another_process_answers() -> None:
    """A join names the process that took it (its boot): a teammate that
    finds another process there -- the joiner died and started again before
    this robot took the post -- counts it down, not waiting for a plan the
    new process never had the post to show.  The process may be named with
    the post, or later (robots joining together learn each other's from the
    post repeated), before or after its state is observed (simulator seed
    20326 of the 3-robot storage and forgery profile: a starved robot
    waited 120 s for a co-joiner's plan)."""
    network = MemoryNetwork()
    states = ObservedStates(network.client(), {"Robot2": endpoint("Robot2")}, PLAN_PATH, liveness=True)
    try:
        states.readmit("Robot2", boot=5)
        await states.watcher.update("Robot2", robot("Robot2", 0, boot=6))
        assert "another process" in states.down["Robot2"]
        states.readmit("Robot2", boot=6)
        await states.watcher.update("Robot2", robot("Robot2", 0, boot=6))
        assert "Robot2" not in states.down
        states.readmit("Robot2")
        await states.watcher.update("Robot2", robot("Robot2", 0, boot=7))
        await states.expect_process("Robot2", 8)  # named after its state arrived
        assert "another process" in states.down["Robot2"]
    finally:
        await states.aclose()
    team = view(MemoryNetwork(), robot("Robot1", 6))
    try:
        await team.membership.named("Robot2", 7, 5)  # before this robot took the post: kept for the admission
        team.membership.admit("Robot2", 7)
        await team._teammates.watcher.update("Robot2", robot("Robot2", 0, boot=9))
        assert not team.is_up("Robot2")
    finally:
        await team.aclose()


async def test_a_co_joiner_the_feeder_says_missed_its_join_is_down() -> None:
    """Robot1 took a join post naming Robot2 too; Robot2 did not take its
    own (killed again, or cut off), and the feeder's repeat says so: any
    process of Robot2 that Robot1 finds is counted out, not waited for
    (simulator seed 337 of nine robots with power cuts: 91 s).  Told
    before Robot1 admitted it, it is kept for the admission (seed 467).
    The repeat of another task's join changes nothing."""
    for told in ("after the admission", "before the admission"):
        team = view(MemoryNetwork(), robot("Robot1", 6))
        try:
            if told == "before the admission":
                await team.membership.missed("Robot2", 7)
            team.membership.admit("Robot2", 7)
            await team.membership.missed("Robot2", 8)
            await team.membership.missed("Robot2", 7)
            await team._teammates.watcher.update("Robot2", robot("Robot2", 0, boot=9))
            assert not team.is_up("Robot2"), told
        finally:
            await team.aclose()
    team = view(MemoryNetwork(), robot("Robot1", 6))
    try:
        team.membership.admit("Robot2", 7)
        await team.membership.missed("Robot2", 8)  # another task's: nothing to do
        await team._teammates.watcher.update("Robot2", robot("Robot2", 0, boot=9))
        assert team.is_up("Robot2")
    finally:
        await team.aclose()


async def test_a_member_the_feeder_says_restarted_during_a_task_is_down_and_gone() -> None:
    """The feeder found Robot2 running again as a new process while it
    posted task 7, and the new process did not take it: the process
    Robot1 counts on is gone, so Robot1 takes its last plan from a teammate
    (as a dead robot's) instead of waiting for the new process to show one
    (simulator seed 5563 of nine robots with power cuts: a joiner that had
    never seen the old process waited for good).  A teammate already left
    out stays as it is."""
    team = view(MemoryNetwork(), robot("Robot1", 6))
    try:
        await team._teammates.watcher.update("Robot2", robot("Robot2", 6, boot=9))
        assert team.is_up("Robot2")
        await team.membership.restarted("Robot2", 7)
        assert not team.is_up("Robot2") and "Robot2" in team._teammates.gone
        assert "restarted while task 7 was decided" in team._teammates.down["Robot2"]
        team.membership.leave_out("Robot3", 5, "down")
        await team.membership.restarted("Robot3", 7)
        assert "Robot3" not in team._teammates.gone
    finally:
        await team.aclose()


async def test_a_left_out_co_joiner_that_missed_its_join_stays_out_in_the_same_epoch() -> None:
    """Robot2, left out, was named a joiner at task 7 beside Robot1 and did
    not take its post; the feeder named it to no teammate, so they keep it
    out in the same epoch, and Robot1 must too, whether the feeder's repeat
    came before its admission or after it (simulator seed 50615: the joiner
    admitted its co-joiner, then left it out again, and named an epoch two
    ahead of its teammate's on every task after).  An admission that a
    decision was made in stays: its epoch is on record."""
    for told in ("before the admission", "after the admission", "after a decision"):
        team = view(MemoryNetwork(), robot("Robot1", 6))
        try:
            team.membership.leave_out("Robot2", 5, "down")
            kept = team.membership.current
            if told == "before the admission":
                await team.membership.missed("Robot2", 7)
            team.membership.admit("Robot2", 7)
            if told != "before the admission":
                await team.membership.missed("Robot2", 7, decided=told == "after a decision")
            if told == "after a decision":
                assert team.membership.current == Membership(kept.epoch + 1, ("Robot1", "Robot2", "Robot3"))
            else:
                assert team.membership.current == kept, told
                assert team.membership.excluded == {"Robot2": 6}, told
        finally:
            await team.aclose()



class OneTeammateNotUpYet:
    """Robot2 answers its observation; Robot3's never comes (not started)."""

    def __init__(self) -> None:
        self.counters = TrafficCounters()

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        await asyncio.Event().wait()
        raise AssertionError("unreachable")

    async def observe(self, peer: Endpoint, request: Request) -> AsyncIterator[Response]:
        if peer.port == 3:
            await asyncio.Event().wait()
        yield Response(Status.CONTENT, state(0).encode_plan(), ContentFormat.CBOR)
        await asyncio.Event().wait()

    async def aclose(self) -> None:
        pass


async def test_a_starting_robot_waits_to_hear_from_its_teammates_a_bounded_time_and_suspects_nobody() -> None:
    endpoints = {"Robot2": Endpoint("coap", "127.0.0.1", 2), "Robot3": Endpoint("coap", "127.0.0.1", 3)}
    states = ObservedStates(OneTeammateNotUpYet(), endpoints, PLAN_PATH, liveness=True)
    states.start()
    try:
        assert await states.heard_from_all(0.3) == ["Robot2"]
        assert states.down == {}  # silence at start is awaited, not counted
        only_robot2 = ObservedStates(OneTeammateNotUpYet(), {"Robot2": endpoints["Robot2"]}, PLAN_PATH)
        only_robot2.start()
        try:
            async with asyncio.timeout(2):  # returns once every teammate is heard, not at the bound
                assert await only_robot2.heard_from_all(60) == ["Robot2"]
        finally:
            await only_robot2.aclose()
    finally:
        await states.aclose()


# --------------------------------------------------------------------------- joins with no survivor

from coapkb.agent.lease import LEASE_PATH  # noqa: E402
from coapkb.agent.observed_states import STATE_PATH  # noqa: E402
from coapkb.agent.robot_state import Decision  # noqa: E402


async def serve_state(network: MemoryNetwork, own: RobotState, *, counts_others: bool = True):
    """A teammate's /robot/state and /robot/plan on the memory network, and
    its answer to ``/robot/lease?r=X&counts`` (``counts_others``)."""
    router = Router()

    async def full(request: Request) -> Response:
        return Response(Status.CONTENT, own.encode(), ContentFormat.CBOR)

    async def plan(request: Request) -> Response:
        return Response(Status.CONTENT, own.encode_plan(), ContentFormat.CBOR)

    async def counts(request: Request) -> Response:
        if counts_others:
            return Response(Status.CONTENT)
        return Response.error(Status.FORBIDDEN, f"{own.robot_id} has {request.query.get('r')} down")

    router.add(ResourceInfo(STATE_PATH, obs=True), full)
    router.add(ResourceInfo(PLAN_PATH, obs=True), plan)
    router.add(ResourceInfo(LEASE_PATH), counts)
    return await network.serve(router, endpoint(own.robot_id))


async def joiner_beside(network: MemoryNetwork, last: Decision) -> TeamView:
    """Robot1, a restarted process (not started), beside Robot3 showing its
    decision ``last`` on the memory network."""
    await serve_state(network, replace(robot("Robot3", last.seq), last=last))
    return view(network, robot("Robot1", 0, boot=3))


async def test_joiners_with_no_surviving_teammate_start_a_fresh_membership_of_the_join_list() -> None:
    """Every robot of a cluster restarted in turn, each before the one
    before had joined: no process that decided task 9 is left.  Robot1
    joins at task 10 with Robot2; Robot3 is a new process that decided
    nothing (restarted after the task was posted), or no process at all.
    Robot1 does not wait for a decision nobody can show: its membership is
    the join list's, its epoch the task's number, as on every joiner
    (simulator seed 3531 of the 3-robot mixed profile: the joiners logged
    "cannot join" and decided nothing)."""
    for robot3 in ("a new process", "no process"):
        network = MemoryNetwork()
        if robot3 == "a new process":
            await serve_state(network, robot("Robot3", 0, boot=7))
        team = view(network, robot("Robot1", 0, boot=3))
        try:
            async with asyncio.timeout(2):
                await team.join(10, patience=60, joining=("Robot1", "Robot2"))
            assert team.membership.excluded == {"Robot3": 9} and team.own.plan.seq == 9
            assert (team.membership.epoch, team.membership.members) == (10, ("Robot1", "Robot2"))
            team.membership.admit("Robot2", 10)  # as the controller does next, on every joiner alike: a member already
            assert team.membership.epoch == 10
        finally:
            await team.aclose()



async def test_a_joiner_that_reaches_no_survivor_takes_the_membership_its_co_joiner_joined_on() -> None:
    """Robot1 and Robot2 join at task 10; Robot3, the survivor that decided
    task 9, died after Robot2 had read its decision and before Robot1 did.
    Robot2's state shows the decision it joined on: Robot1 takes the same
    membership, not a fresh one, and shows it in turn (simulator seed
    103234 of three robots with power cuts: the joiner starved of CPU
    started a fresh membership, its co-joiner had joined the survivor's,
    and the two decided in two epochs).  A co-joiner that joined on
    nothing, or is still joining when ``patience`` runs out, leaves the
    fresh membership of the join list; one past the task without Robot1
    left it out."""
    on = Decision(9, "Gucci_bag_14", assigned_to="Robot3", epoch=4, members=("Robot2", "Robot3"))
    cases = {"joined on Robot3's decision": (replace(robot("Robot2", 9, boot=5), joined=on), (5, ("Robot1", "Robot2",
                                                                                                  "Robot3"))),
             "joined on nothing": (robot("Robot2", 9, boot=5), (10, ("Robot1", "Robot2"))),
             "still joining": (robot("Robot2", 0, boot=5), (10, ("Robot1", "Robot2"))),
             # Gone on without Robot1: it was left out, a membership of its own, alone.
             "past the task without it": (replace(robot("Robot2", 10, boot=5), last=replace(on, seq=10, epoch=5)),
                                          (10, ("Robot1",)))}
    for case, (robot2, expected) in cases.items():
        network = MemoryNetwork()
        await serve_state(network, robot2)
        team = view(network, robot("Robot1", 0, boot=3))
        try:
            async with asyncio.timeout(2):
                admits = await team.join(10, patience=0.2, joining=("Robot1", "Robot2"))
            assert admits == (robot2.last is None), case
            if admits:
                team.membership.admit("Robot2", 10)  # as the controller does next
            assert (team.membership.epoch, team.membership.members) == expected, case
            assert team.own.joined == (on if robot2.joined else None), case
        finally:
            await team.aclose()

async def test_a_joiner_takes_the_membership_a_survivor_decided_the_task_before_in() -> None:
    network = MemoryNetwork()
    last = Decision(9, "Gucci_bag_14", assigned_to="Robot3", epoch=4, members=("Robot2", "Robot3"))
    team = await joiner_beside(network, last)
    try:
        async with asyncio.timeout(2):
            await team.join(10, patience=60, joining=("Robot1",))
        assert (team.membership.epoch, team.membership.members) == (5, ("Robot1", "Robot2", "Robot3"))
    finally:
        await team.aclose()


async def test_a_joiner_takes_the_membership_of_its_own_task_when_a_teammate_decided_it_counting_it() -> None:
    """Robot3 admitted Robot1 at task 10 and decided that task without a
    plan of it (a repeat, skipped on its claim): it shows task 10, not 9,
    with Robot1 a member.  The joiner takes that membership, not one of its
    own (found in the simulator with the rejoin fault, seeds 58 and 143: a
    joiner alone in a membership gave an object again)."""
    network = MemoryNetwork()
    last = Decision(10, "Gucci_bag_14", skipped=True, epoch=4, members=("Robot1", "Robot2", "Robot3"))
    team = await joiner_beside(network, last)
    try:
        async with asyncio.timeout(2):
            await team.join(10, patience=60, joining=("Robot1", "Robot2"))
        assert (team.membership.epoch, team.membership.members) == (4, ("Robot1", "Robot2", "Robot3"))
    finally:
        await team.aclose()


async def test_a_joiner_a_survivor_went_on_without_is_left_out_alone() -> None:
    """Robot3, the survivor, decided task 10 in a membership without
    Robot1, cut off until then: Robot1 is left out.  Its membership is its
    own, alone, and it says so (it admits no co-joiner): named with its
    co-joiner Robot2, which had joined in Robot3's membership, it looked a
    majority to the feeder, and the cluster split (simulator seeds 314, 870
    and 902 of the rejoin profile)."""
    network = MemoryNetwork()
    last = Decision(10, "Gucci_bag_14", assigned_to="Robot3", epoch=6, members=("Robot2", "Robot3"))
    team = await joiner_beside(network, last)
    try:
        async with asyncio.timeout(2):
            joined = await team.join(10, patience=60, joining=("Robot1", "Robot2"))
        assert not joined
        assert team.membership.members == ("Robot1",) and set(team.membership.excluded) == {"Robot2", "Robot3"}
    finally:
        await team.aclose()


async def test_a_teammate_the_joined_decision_costs_and_first_seen_earlier_is_a_restart() -> None:
    """Robot1 joins at task 10 on Robot3's decision of task 9, computed on
    Robot2's plan after task 8.  Robot1 was cut off and never observed
    Robot2, which restarted meanwhile: its first state shows task 0, so it
    is a new process, down until it joins, not the member waited for
    (simulator seed 420 of the rejoin profile: the joiner waited for its
    plan for good)."""
    network = MemoryNetwork()
    last = Decision(9, "Gucci_bag_14", assigned_to="Robot3", costs={"Robot2": 3.0, "Robot3": 1.0}, epoch=4,
                    members=("Robot2", "Robot3"))
    team = await joiner_beside(network, last)
    try:
        async with asyncio.timeout(2):
            assert await team.join(10, patience=60, joining=("Robot1",))
        await serve_state(network, robot("Robot2", 0, boot=11))
        async with asyncio.timeout(5):
            assert "restarted" in await team.until_down("Robot2")
    finally:
        await team.aclose()


async def test_a_joiner_waits_for_a_silent_teammate_and_observes_it_again_rather_than_leave_it_out() -> None:
    """Robot3 decided task 9 but is cut off from the joiner: its first
    observation is never answered.  The joiner does not start a membership
    of its own after a wait (Robot3 and the co-joiner that reached it decide
    on in Robot3's): it observes Robot3 again and takes its membership once
    the partition heals (simulator seed 1114 of nine robots with power cuts:
    two joiners in two memberships, one of them without the survivor)."""
    network = MemoryNetwork()
    last = Decision(9, "Gucci_bag_14", assigned_to="Robot3", epoch=4, members=("Robot2", "Robot3"))
    own = replace(robot("Robot3", 9), last=last)
    asked = 0

    async def state_after_the_partition(request: Request) -> Response:
        nonlocal asked
        asked += 1
        if asked == 1:
            await asyncio.Event().wait()  # lost in the partition
        return Response(Status.CONTENT, own.encode(), ContentFormat.CBOR)

    router = Router()
    router.add(ResourceInfo(STATE_PATH, obs=True), state_after_the_partition)
    await network.serve(router, endpoint("Robot3"))
    team = view(network, robot("Robot1", 0, boot=3))
    try:
        async with asyncio.timeout(5):
            await team.join(10, patience=0.2, joining=("Robot1", "Robot2"))
        assert asked == 2
        assert (team.membership.epoch, team.membership.members) == (5, ("Robot1", "Robot2", "Robot3"))
    finally:
        await team.aclose()


# --------------------------------------------------------------------------- the one cut off

async def cut_off(network: MemoryNetwork, own: RobotState) -> TeamView:
    """``own``'s view of Robot2 and Robot3 (served on ``network``), started,
    with both teammates seen once and then declared down for their silence."""
    team = view(network, own)
    team.start()
    try:
        await team._teammates.wait(lambda s: {"Robot2", "Robot3"} <= set(s), timeout=2)
        for teammate in ("Robot2", "Robot3"):
            await team._teammates.declare_down(teammate, "2 requests failed in a row")
    except BaseException:
        await team.aclose()
        raise
    return team


async def test_a_robot_outnumbered_counts_again_on_teammates_that_answer_and_never_grants_them() -> None:
    """Robot1, cut off, declared both teammates down; they went on counting
    it.  Once one answers as the same process, Robot1 waits for its plans
    and asks it again (no majority of its own, it decided alone against
    them: simulator seeds 20025 and 20056 of the 9-robot freeze and
    partition profile), but never grants it a lease again (the fence).  A
    new process of a teammate is not taken for the old one: it joins."""
    network = MemoryNetwork()
    await serve_state(network, robot("Robot2", 4, boot=2))
    robot3 = await serve_state(network, robot("Robot3", 4, boot=3))
    team = await cut_off(network, robot("Robot1", 4))
    try:
        await robot3.aclose()
        await serve_state(network, robot("Robot3", 0, boot=9))  # restarted meanwhile
        assert team.membership.alone
        assert not await team.revival.heard_again("Robot3") and not team.is_up("Robot3")
        assert await team.revival.heard_again("Robot2")
        assert team.is_up("Robot2") and not team.membership.alone
        assert "never grants" in (team.membership.grant("Robot2") or "")
        await team._teammates.wait(lambda s: s["Robot2"].plan.seq == 4, timeout=2)
        team.membership.admit("Robot2", 5)  # a new process of it, joining: granted again
        assert team.membership.grant("Robot2") is None
    finally:
        await team.aclose()


@pytest.mark.parametrize("robot2", [
    replace(robot("Robot2", 5, boot=2),
            last=Decision(5, "Muji_rug_426", assigned_to="Robot3", epoch=1, members=("Robot2", "Robot3"))),
    robot("Robot2", 5, boot=2),
], ids=["went on without it", "has it down"])
async def test_a_teammate_that_does_not_count_the_robot_cut_off_is_not_counted_on_again(robot2: RobotState) -> None:
    """Robot1, cut off, declared both teammates down; Robot2 answers as the
    same process, but does not count Robot1: its last decision left Robot1
    out (epoch 1, members Robot2 and Robot3), or it has Robot1 down with
    Robot3 up and leaves it out at its next task.  So Robot1 does not count
    on it either.  Counted on again, Robot1 left Robot3 out with Robot2 in
    an epoch 1 of its own, and the two epochs 1 disagreed (simulator: nine
    robots with power cuts, seed 4496; nine robots with partitions, seed
    2716)."""
    network = MemoryNetwork()
    await serve_state(network, robot2, counts_others=robot2.last is not None)
    await serve_state(network, robot("Robot3", 5, boot=3))
    team = await cut_off(network, robot("Robot1", 4))
    try:
        assert not await team.revival.heard_again("Robot2")
        assert not team.is_up("Robot2") and team.membership.alone
    finally:
        await team.aclose()


def test_a_robot_alone_still_counts_the_teammates_it_has_down() -> None:
    """Asked ``counts``, a robot answers whether it counts a teammate as up
    and a member: not one it has down, unless it is alone (that suspicion
    is its own: two robots cut off from each other, each alone, count each
    other again), nor one it left out; a process refused a lease is counted."""
    team = view(MemoryNetwork(), robot("Robot1", 4))
    membership = team.membership
    team._teammates.down["Robot2"] = "2 requests failed in a row"
    assert "has Robot2 down" in (membership.counts("Robot2") or "")
    team._teammates.down["Robot3"] = "2 requests failed in a row"
    assert membership.alone and membership.counts("Robot2") is None
    del team._teammates.down["Robot3"]
    membership.leave_out("Robot3", 4, "cut off")
    assert "left Robot3 out" in (membership.counts("Robot3") or "")
    del team._teammates.down["Robot2"]
    membership.refused.add("Robot2")
    assert membership.counts("Robot2") is None and "never grants" in (membership.grant("Robot2") or "")
    assert "not in this robot's cluster" in (membership.counts("Robot9") or "")


async def test_an_outnumbered_robot_leaves_no_teammate_out_for_its_silence() -> None:
    """Robot1, cut off, has both teammates down for their silence and no
    plan of Robot2 after task 4: it may be the one cut off while they
    decide on, counting it, so it leaves nobody out (a membership of its
    own, an epoch ahead, voided theirs in the record: simulator seed 356 of
    the 3-robot swarm profile with writes).  A teammate whose process is
    known gone (nobody listening there) leaves as before."""
    network = MemoryNetwork()
    await serve_plan(network, robot("Robot2", 3))
    await serve_plan(network, robot("Robot3", 4))
    team = await cut_off(network, robot("Robot1", 4))
    try:
        with pytest.raises(TransportError, match="leaves nobody out"):
            await team.planned_states(4, timeout=2)
        assert team.membership.excluded == {} and team.membership.epoch == 0
        team._teammates.down.pop("Robot2")
        team._teammates.gone.add("Robot2")
        await team._teammates.declare_down("Robot2", "port unreachable")
        plans = await team.planned_states(4, timeout=2)
        assert set(plans) == {"Robot1", "Robot3"} and team.membership.excluded == {"Robot2": 5}
        assert team.membership.epoch == 1
    finally:
        await team.aclose()


async def test_an_admission_is_a_new_epoch_only_for_a_robot_left_out() -> None:
    """A restarted robot the membership still counts (restarted before the
    others left it out) is admitted in the same epoch, on every robot alike,
    whether or not the task's join list named it to them (the feeder names to
    the teammates only the joiners its post reached: simulator seed 1621 of
    the 3-robot swarm profile with writes); one left out comes back in a new
    epoch.  A joiner reads the same from the membership it joins on."""
    network = MemoryNetwork()
    team = view(network, robot("Robot1", 4))
    try:
        team.membership.admit("Robot2", 5)
        assert team.membership.epoch == 0
        team.membership.excluded["Robot3"] = 4
        team.membership.epoch = 1
        team.membership.admit("Robot3", 5)
        assert (team.membership.epoch, team.membership.members) == (2, ("Robot1", "Robot2", "Robot3"))
    finally:
        await team.aclose()
    last = Decision(9, "Gucci_bag_14", assigned_to="Robot3", epoch=4, members=("Robot1", "Robot2", "Robot3"))
    joiner = await joiner_beside(network, last)
    try:
        async with asyncio.timeout(2):
            await joiner.join(10, patience=60, joining=("Robot1", "Robot2"))
        joiner.membership.admit("Robot2", 10)
        assert (joiner.membership.epoch, joiner.membership.members) == (4, ("Robot1", "Robot2", "Robot3"))
    finally:
        await joiner.aclose()


class BackDuringTheProbe:
    """A teammate silent to every request until the indirect probe runs:
    meanwhile it is back, and a notification of its observation arrives,
    while the helper's own answer is lost."""

    def __init__(self) -> None:
        self.counters = TrafficCounters()
        self.back = asyncio.Event()

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        raise PeerTimeout(f"{peer}: no answer within {timeout}s")

    async def observe(self, peer: Endpoint, request: Request) -> AsyncIterator[Response]:
        yield Response(Status.CONTENT, robot("Robot2", 1).encode_plan(), ContentFormat.CBOR)
        await self.back.wait()
        yield Response(Status.CONTENT, robot("Robot2", 2).encode_plan(), ContentFormat.CBOR)
        await asyncio.Event().wait()

    async def aclose(self) -> None:
        pass


async def test_a_teammate_heard_from_while_its_silence_is_confirmed_is_not_declared_down() -> None:
    """Two requests to Robot2 failed (it was frozen); the teammate asked to
    reach it fails too, but Robot2's own notification came meanwhile: its
    silence is over and it stays up (simulator seed 1534 of the 3-robot swarm
    profile with writes: declared down a second after its notifications came
    again, a robot decided a task alone)."""
    transport = BackDuringTheProbe()
    states = ObservedStates(transport, {"Robot2": Endpoint("coap", "127.0.0.1", 1)}, PLAN_PATH, liveness=True)

    async def helper_fails(robot_id: str) -> bool:
        transport.back.set()
        await states.wait(lambda s: s["Robot2"].plan.seq == 2, timeout=2)
        return False

    states.confirm_silence = helper_fails
    states.start()
    try:
        await states.wait(lambda s: "Robot2" in s, timeout=2)
        for _ in range(2):
            await states.record_failure("Robot2", PeerTimeout("no answer"))
        assert "Robot2" not in states.down
        await states.record_failure("Robot2", PeerTimeout("no answer"))
        await states.record_failure("Robot2", PeerTimeout("no answer"))
        assert "Robot2" in states.down and "Robot2" not in states.gone  # silent again, nothing heard: down
    finally:
        await states.aclose()


async def test_a_restart_told_of_a_task_before_the_join_leaves_the_new_process_up() -> None:
    """Robot2 restarted and joined at task 7; a try of task 6's post naming
    it restarted, held back on the way, comes now: it is about the process
    that left, not the one just admitted (simulator, three robots with
    messages held back, seed 28: Robot3 alone left the new process out).
    Told of the join's own task, it is a later restart, and counts."""
    team = view(MemoryNetwork(), robot("Robot1", 6))
    try:
        team.membership.admit("Robot2", 7)
        await team._teammates.watcher.update("Robot2", robot("Robot2", 6, boot=9))
        await team.membership.restarted("Robot2", 6)
        assert team.is_up("Robot2")
        await team.membership.restarted("Robot2", 7)
        assert not team.is_up("Robot2")
    finally:
        await team.aclose()


async def test_a_leader_down_here_that_sends_its_decision_in_this_robots_membership_is_counted_on_again() -> None:
    """Robot1 had Robot2 (its leader, compute and communicate) down from a
    cut that healed while no task came; Robot3 is up, so Robot1 is not
    alone and would not count Robot2 again on an answer.  Robot2's decision
    in Robot1's own membership (its epoch, both members) shows the suspicion
    stale: Robot2 is counted on again, never granted a lease (simulator,
    six robots, seed 21881: the follower decided the next task alone,
    leaving out the leader its teammate followed).  A decision of another
    epoch, or of another process, changes nothing."""
    network = MemoryNetwork()
    await serve_state(network, robot("Robot2", 4, boot=2))
    await serve_state(network, robot("Robot3", 4, boot=3))
    team = view(network, robot("Robot1", 4))
    team.start()
    try:
        await team._teammates.wait(lambda s: {"Robot2", "Robot3"} <= set(s), timeout=2)
        await team._teammates.declare_down("Robot2", "2 requests failed in a row")
        assert not team.membership.alone
        members = ("Robot1", "Robot2", "Robot3")
        assert not team.revival.led_by("Robot2", 2, Membership(team.membership.epoch + 1, members))
        assert not team.revival.led_by("Robot2", 7, Membership(team.membership.epoch, members))
        assert not team.revival.led_by("Robot2", 2, Membership(team.membership.epoch, ("Robot2", "Robot3")))
        assert team.revival.led_by("Robot2", 2, Membership(team.membership.epoch, members))
        await team._teammates.wait(lambda _: team.is_up("Robot2"), timeout=2)
        assert "never grants" in (team.membership.grant("Robot2") or "")
    finally:
        await team.aclose()
