"""The lease (the fence for a robot that was only cut off): how many
grants a robot needs, when a round is a refusal and when only undecided,
that the lease runs from the round's send time, and who a teammate grants."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from types import SimpleNamespace
from typing import Any, cast

from coapkb.agent.lease import LEASE_PATH, Lease, lease_duration_s
from coapkb.agent.robot_resources import RobotResources
from coapkb.agent.robot_state import Decision, LiveState, PlannedState, RobotState
from coapkb.agent.team_view import TeamView
from coapkb.transport.base import Endpoint, PeerUnreachable
from coapkb.transport.messages import Method, Request, Response, Status

MATES = {"Robot1": Endpoint("coap", "127.0.0.1", 1), "Robot3": Endpoint("coap", "127.0.0.1", 3)}


class Scripted:
    """A client whose peers answer as told: "grant", "refuse" or "silent"."""

    def __init__(self, answers: dict[int, str], delay_s: float = 0.0) -> None:
        self.answers = answers
        self.delay_s = delay_s
        self.asked: list[tuple[int, Request]] = []

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        self.asked.append((peer.port, request))
        await asyncio.sleep(self.delay_s)
        answer = self.answers[peer.port]
        if answer == "silent":
            raise PeerUnreachable(f"no answer from {peer}")
        if answer == "refuse":
            return Response.error(Status.FORBIDDEN, "Robot1 has Robot2 down")
        if answer == "not yet":
            return Response.error(Status.SERVICE_UNAVAILABLE, "Robot3 has not decided that task yet")
        return Response(Status.CONTENT)

    def observe(self, peer: Endpoint, request: Request) -> AsyncIterator[Response]:
        raise NotImplementedError

    async def aclose(self) -> None:
        pass


def _lease(client: Scripted, down: dict[str, str] | None = None, failures: list[str] | None = None,
           left_out: dict[str, int] | None = None) -> Lease:
    async def failed(robot_id: str, exc: Exception) -> None:
        (failures if failures is not None else []).append(robot_id)

    return Lease("Robot2", MATES, client, 3.0, request_timeout_s=lambda: 1.0, down=lambda: down or {},
                 left_out=lambda: left_out or {}, on_failure=failed)


async def test_one_grant_of_two_teammates_is_a_majority_of_three() -> None:
    client = Scripted({1: "refuse", 3: "grant"})
    lease = _lease(client)
    assert lease.needed == 1
    sent = time.monotonic()
    assert await lease.hold(0.1) is None
    # Valid from the round's send time, not from the answer.
    assert sent <= lease.valid_until - 3.0 <= time.monotonic()
    assert all(r.path == LEASE_PATH and r.query == {"r": "Robot2"} for _, r in client.asked)
    # Held: no new round while it covers what is asked.
    asked = len(client.asked)
    assert await lease.hold(0.1) is None and len(client.asked) == asked


async def test_refused_by_all_is_fenced_with_the_reasons() -> None:
    why = await _lease(Scripted({1: "refuse", 3: "refuse"})).hold(0.1)
    assert why is not None and "no lease from a majority" in why and "Robot1: refused" in why
    # A teammate this robot has down counts as a refusal; one that does not
    # answer is reported to failure detection.
    failures: list[str] = []
    why = await _lease(Scripted({1: "silent", 3: "refuse"}), down={"Robot1": "2 requests failed"},
                       failures=failures).hold(0.1)
    assert why is not None and "Robot1: down" in why and not failures


async def test_no_answers_wait_and_never_grant() -> None:
    failures: list[str] = []
    client = Scripted({1: "silent", 3: "silent"})
    lease = _lease(client, failures=failures)
    try:
        async with asyncio.timeout(0.5):
            await lease.hold(0.1)
        raise AssertionError("a silent cluster granted a lease")
    except TimeoutError:
        pass
    assert len(client.asked) >= 4 and set(failures) == {"Robot1", "Robot3"}
    assert lease.valid_until == float("-inf")


async def test_a_cluster_of_one_needs_nobody() -> None:
    lease = Lease("Robot1", {}, Scripted({}), 3.0, request_timeout_s=lambda: 1.0, down=dict)
    assert lease.needed == 0 and await lease.hold(1.0) is None


def test_lease_length_follows_the_liveness_floor() -> None:
    assert lease_duration_s(1.0) == 3.0 and lease_duration_s(5.0) == 15.0


async def test_a_teammate_grants_only_a_member_it_has_up() -> None:
    own = RobotState("Robot1", PlannedState(1, 0, 400.0, 0.0, 40.0), LiveState(1.0, 0.0))
    team = TeamView(own, {"Robot2": Endpoint("coap", "127.0.0.1", 2), "Robot3": Endpoint("coap", "127.0.0.1", 3)},
                    Scripted({}))
    assert team.membership.grant("Robot2") is None
    assert "not in this robot's cluster" in (team.membership.grant("Robot9") or "")
    team.membership.excluded["Robot3"] = 5
    assert "left Robot3 out" in (team.membership.grant("Robot3") or "")
    await team._teammates.declare_down("Robot2", "2 requests failed in a row")
    assert "Robot1 has Robot2 down" in (team.membership.grant("Robot2") or "")


async def test_a_lease_for_a_later_task_is_asked_again_and_names_it() -> None:
    """A lease granted for task 4 still runs, but a job of task 5 asks
    again, naming the task: a teammate grants it only once it decided task
    5 with this robot a member."""
    client = Scripted({1: "grant", 3: "grant"})
    lease = _lease(client)
    assert await lease.hold(0.1, 4) is None
    asked = len(client.asked)
    assert await lease.hold(0.1, 4) is None and len(client.asked) == asked  # held for task 4
    assert await lease.hold(0.1, 5) is None and len(client.asked) > asked
    assert client.asked[-1][1].query == {"r": "Robot2", "t": "5"}


async def test_a_teammate_grants_a_task_only_once_it_decided_it_with_the_robot_a_member() -> None:
    """Robot1 left Robot2 out of task 6 on (Robot2 cut off, still granted
    from before): Robot2's job of task 6, decided as a member, not knowing,
    is refused; a task Robot1 has not decided yet is "not yet" (5.03, the
    holder asks again); one decided with Robot2 a member is granted (the
    simulator's "pick at the edge of an exclusion", section 4 of
    docs/simulation.md)."""
    own = RobotState("Robot1", PlannedState(1, 0, 400.0, 0.0, 40.0, seq=6), LiveState(1.0, 0.0),
                     last=Decision(6, "Apple", assigned_to="Robot1", epoch=1, members=("Robot1", "Robot3")))
    team = TeamView(own, {"Robot2": Endpoint("coap", "127.0.0.1", 2), "Robot3": Endpoint("coap", "127.0.0.1", 3)},
                    Scripted({}))
    log = [Decision(5, "Pear", assigned_to="Robot2"), own.last]
    resources = RobotResources(cast(Any, SimpleNamespace(robot_id="Robot1")), team,
                               cast(Any, SimpleNamespace(log=log)), cast(Any, None), cast(Any, None))

    async def ask(query: dict[str, str]) -> Response:
        return await resources._get_lease(Request(Method.GET, LEASE_PATH, query))

    assert (await ask({"r": "Robot2", "t": "5"})).status == Status.CONTENT
    refused = await ask({"r": "Robot2", "t": "6"})
    assert refused.status == Status.FORBIDDEN and "decided task 6 without Robot2" in refused.text()
    assert (await ask({"r": "Robot3", "t": "7"})).status == Status.SERVICE_UNAVAILABLE
    assert (await ask({"r": "Robot3", "t": "seven"})).status == Status.BAD_REQUEST


async def test_a_process_that_decided_nothing_yet_grants_only_before_it_takes_a_post() -> None:
    """Before its first post (the run's start, or restarted and not joined
    yet) a process grants by the membership alone: it may decide nothing
    before the cluster's jobs are done.  Once it took task 1's post it
    decides it, and says "not yet" until then (simulator, nine robots with
    partitions, seed 116: it granted a teammate cut off from it, then left
    that teammate out of task 1)."""
    own = RobotState("Robot1", PlannedState(1, 0, 400.0, 0.0, 40.0), LiveState(1.0, 0.0))
    team = TeamView(own, {"Robot2": Endpoint("coap", "127.0.0.1", 2), "Robot3": Endpoint("coap", "127.0.0.1", 3)},
                    Scripted({}))
    resources = RobotResources(cast(Any, SimpleNamespace(robot_id="Robot1")), team,
                               cast(Any, SimpleNamespace(log=[])), cast(Any, None), cast(Any, None))

    async def ask() -> Response:
        return await resources._get_lease(Request(Method.GET, LEASE_PATH, {"r": "Robot2", "t": "1"}))

    assert (await ask()).status == Status.CONTENT
    resources.accepted[1] = "Apple"
    not_yet = await ask()
    assert not_yet.status == Status.SERVICE_UNAVAILABLE and "has not decided task 1 yet" in not_yet.text()


async def test_a_teammate_left_out_before_the_task_is_no_granter() -> None:
    """Robot2 has Robot1 down and left Robot3 out from task 12: for a job of
    task 14 no majority can grant, and it is fenced at once.  Robot3, never
    fed that task, said "not yet" for good, and the job waited with it
    (simulator, nine robots with partitions, seed 9188).  For a job of a
    task before it left Robot3 out, Robot3 is asked as before."""
    client = Scripted({1: "silent", 3: "not yet"})
    lease = _lease(client, down={"Robot1": "2 requests failed in a row"}, left_out={"Robot3": 12})
    why = await asyncio.wait_for(lease.hold(0.1, 14), timeout=2)
    assert why is not None and "left out of this robot's membership from task 12" in why and not client.asked
    client.answers[3] = "grant"
    lease = _lease(client, down={"Robot1": "2 requests failed in a row"}, left_out={"Robot3": 12})
    assert await lease.hold(0.1, 11) is None and client.asked[-1][1].query == {"r": "Robot2", "t": "11"}
