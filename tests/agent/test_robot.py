"""A whole robot (coapkb.agent.robot.Robot) in this process: its KB, CoAP
server and workflow modules on loopback with real sockets, asked through its
resources as a teammate or the feeder would."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator

import cbor2
import pytest
import pytest_asyncio
from support import KB_FILES, free_udp_port

from coapkb.agent.controller import RobotBounds
from coapkb.agent.robot import Robot
from coapkb.agent.robot_state import RobotState
from coapkb.config import ExecutionModel, RobotConfig, StartState, Teammate
from coapkb.transport import open_client
from coapkb.transport.base import ClientTransport, Endpoint
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status

#: How long a test waits for the robot to get somewhere (generous: a loaded machine).
PATIENCE_S = 30.0


def solo_config(port: int) -> RobotConfig:
    """Robot1 alone, holding all three KB modules: every task is decided here."""
    bind = Endpoint("coap", "127.0.0.1", port)
    return RobotConfig(
        robot_id="Robot1", bind=bind, kb_files=tuple(KB_FILES),  # type: ignore[arg-type]
        team={"Robot1": Teammate("Robot1", bind, ("Location", "Object", "Capability"))},
        start=StartState(aisle=1, rack=1), query_timeout_s=PATIENCE_S, lease_s=0,
        execution=ExecutionModel(time_scale=1e6),
    )


class Asker:
    """A client of one robot's resources."""

    def __init__(self, client: ClientTransport, robot: Endpoint) -> None:
        self.client, self.robot = client, robot

    async def __call__(self, method: Method, path: str, payload: bytes = b"", **kw: object) -> Response:
        request = Request(method, path, payload=payload, **kw)  # type: ignore[arg-type]
        return await self.client.request(self.robot, request, timeout=PATIENCE_S)

    async def post_task(self, seq: int, name: str) -> Response:
        body = json.dumps({"seq": seq, "object": name}).encode()
        return await self(Method.POST, "/tasks", body, content_format=ContentFormat.JSON)

    async def decisions(self, count: int) -> list[dict]:
        """``GET /tasks`` until it lists ``count`` decisions."""
        async with asyncio.timeout(PATIENCE_S):
            while True:
                answer = await self(Method.GET, "/tasks", accept=ContentFormat.JSON)
                assert answer.status == Status.CONTENT, answer
                log = json.loads(answer.payload)
                if len(log) >= count:
                    return log
                await asyncio.sleep(0.05)  # the robot has no event to wait on over the network: ask again


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def ask() -> AsyncIterator[Asker]:
    robot = await Robot.start(solo_config(free_udp_port()))
    client = await open_client("coap")
    try:
        yield Asker(client, robot.config.bind)
    finally:
        await client.aclose()
        await robot.aclose()


pytestmark = pytest.mark.asyncio(loop_scope="module")


async def test_state_and_plan_in_cbor_and_json(ask: Asker) -> None:
    state = await ask(Method.GET, "/robot/state")
    assert state.status == Status.CONTENT and state.content_format == ContentFormat.CBOR
    assert RobotState.decode(state.payload).robot_id == "Robot1"
    as_json = await ask(Method.GET, "/robot/state", accept=ContentFormat.JSON)
    assert json.loads(as_json.payload)["robot_id"] == "Robot1"
    plan = RobotState.decode((await ask(Method.GET, "/robot/plan")).payload)
    assert plan.robot_id == "Robot1" and plan.plan.seq >= 0


async def test_unknown_teammate_or_format_is_a_clear_4xx(ask: Asker) -> None:
    nobody = await ask(Method.GET, "/robot/plan", query={"of": "Robot9"})
    assert nobody.status == Status.NOT_FOUND and "Robot9" in nobody.text()
    bad_at = await ask(Method.GET, "/robot/plan", query={"of": "Robot9", "at": "soon"})
    assert bad_at.status == Status.BAD_REQUEST and "task number" in bad_at.text()
    text = await ask(Method.GET, "/robot/state", accept=ContentFormat.TEXT)
    assert text.status == Status.NOT_ACCEPTABLE and "cbor" in text.text()


async def test_comparing_notes_on_a_teammate_s_plan_is_a_post(ask: Asker) -> None:
    """``?of=X&at=S`` commits the robot asked to go on without X's plan if it
    has none: a POST; a GET of the same only reads."""
    unknown = await ask(Method.POST, "/robot/plan", query={"of": "Robot2", "at": "3"})
    assert unknown.status == Status.NOT_FOUND and "after task 3" in unknown.text()
    incomplete = await ask(Method.POST, "/robot/plan", query={"of": "Robot2"})
    assert incomplete.status == Status.BAD_REQUEST and "of=ROBOT&at=SEQ" in incomplete.text()
    read = await ask(Method.GET, "/robot/plan", query={"of": "Robot2", "at": "3"})
    assert read.status == Status.NOT_FOUND


@pytest.mark.parametrize(
    ("payload", "content_format", "says"),
    [
        (b"\xff not cbor", None, "expected"),
        (b"{not json", ContentFormat.JSON, "expected"),
        (json.dumps({"seq": 1}).encode(), ContentFormat.JSON, "expected"),
        (json.dumps({"seq": "one", "object": "Gucci_bag_14"}).encode(), ContentFormat.JSON, "integer"),
        (cbor2.dumps({"seq": 1, "object": "no spaces please"}), None, "local name"),
        (cbor2.dumps({"seq": 1, "object": "Gucci_bag_14", "join": ["Robot9"]}), None, "join"),
        (cbor2.dumps({"seq": 1, "object": "Gucci_bag_14", "join": [["Robot1"]]}), None, "[robot, boot]"),
        (cbor2.dumps({"seq": 1, "object": "Gucci_bag_14", "join": [["Robot1", -3]]}), None, "[robot, boot]"),
    ],
)
async def test_a_bad_task_body_is_400_with_what_was_expected(
    ask: Asker, payload: bytes, content_format: int | None, says: str
) -> None:
    answer = await ask(Method.POST, "/tasks", payload, content_format=content_format)
    assert answer.status == Status.BAD_REQUEST and says in answer.text(), answer


async def test_a_joiner_answers_its_post_with_its_process() -> None:
    """A robot named to join at a task answers the post with its process
    (its boot), again on a repeat: the feeder names that process to the
    teammates, who take another one found there for a restart."""
    robot = await Robot.start(solo_config(free_udp_port()))
    client = await open_client("coap")
    try:
        ask = Asker(client, robot.config.bind)
        post = cbor2.dumps({"seq": 4, "object": "Gucci_bag_14", "join": [["Robot1", 77]]})
        for _ in range(2):
            answer = await ask(Method.POST, "/tasks", post)
            assert answer.status == Status.CHANGED
            assert cbor2.loads(answer.payload) == {"boot": robot.team.own.boot}
        other = await ask(Method.POST, "/tasks", cbor2.dumps({"seq": 5, "object": "Gucci_bag_1"}))
        assert other.status == Status.CHANGED and other.payload == b""
    finally:
        await client.aclose()
        await robot.aclose()


async def test_a_robot_that_took_tasks_joins_again_where_the_feeder_names_it() -> None:
    """A robot its teammates left out is fed nothing for a while, then named
    to join at a later task: it takes that task (its next), where any
    other task past its next is refused."""
    robot = await Robot.start(solo_config(free_udp_port()))
    client = await open_client("coap")
    try:
        ask = Asker(client, robot.config.bind)
        assert (await ask.post_task(1, "Gucci_bag_14")).status == Status.CHANGED
        assert (await ask.post_task(4, "Gucci_bag_1")).status == Status.CONFLICT  # not named to join
        joined = await ask(Method.POST, "/tasks", cbor2.dumps({"seq": 4, "object": "Gucci_bag_1", "join": ["Robot1"]}))
        assert joined.status == Status.CHANGED and cbor2.loads(joined.payload) == {"boot": robot.team.own.boot}
        assert (await ask.post_task(5, "Gucci_bag_14")).status == Status.CHANGED
        assert [d["seq"] for d in await ask.decisions(3)] == [1, 4, 5]
    finally:
        await client.aclose()
        await robot.aclose()


async def test_a_final_state_goes_confirmed_on_either_resource() -> None:
    """The state a robot ends in (idle, nothing queued, nothing decided
    since) is notified confirmable on ``/robot/outcome`` and on
    ``/robot/state``, which a feeder making a recording observes instead:
    nothing later would make up for its loss."""
    robot = await Robot.start(solo_config(free_udp_port()))
    client = await open_client("coap")

    async def confirmed() -> list[bool]:
        return [(await robot.router.handle(Request(Method.GET, path, accept=accept))).confirm
                for path in ("/robot/state", "/robot/outcome")
                for accept in (ContentFormat.CBOR, ContentFormat.JSON) if (path, accept) != ("/robot/outcome",
                                                                                              ContentFormat.JSON)]

    try:
        assert await confirmed() == [False, False, False]  # never went idle after a job
        ask = Asker(client, robot.config.bind)
        assert (await ask.post_task(1, "Gucci_bag_14")).status == Status.CHANGED
        await ask.decisions(1)  # decided here: the job is queued as the decision is logged
        async with asyncio.timeout(PATIENCE_S):
            await robot.executor.wait_idle()
        assert robot.team.own.live.done == 1
        assert await confirmed() == [True, True, True]
    finally:
        await client.aclose()
        await robot.aclose()


async def test_a_bad_decision_is_400(ask: Asker) -> None:
    answer = await ask(Method.POST, "/decisions", cbor2.dumps({"seq": "x"}))
    assert answer.status == Status.BAD_REQUEST and "not a decision" in answer.text()


async def test_tasks_in_order_are_decided_and_shown_in_stats(ask: Asker) -> None:
    assert (await ask.post_task(1, "Gucci_bag_14")).status == Status.CHANGED
    assert (await ask.post_task(1, "Gucci_bag_14")).status == Status.CHANGED  # a repeat: same answer
    skipped = await ask.post_task(3, "Gucci_bag_1")
    assert skipped.status == Status.CONFLICT and "expected task 2" in skipped.text()
    assert (await ask.post_task(2, "Nonexistent_widget_1")).status == Status.CHANGED
    first, second = await ask.decisions(2)
    assert (first["seq"], first["object"], first["assigned_to"], first["error"]) == (1, "Gucci_bag_14", "Robot1", None)
    assert (second["seq"], second["skipped"]) == (2, True)
    stats = await ask(Method.GET, "/robot/stats", accept=ContentFormat.JSON)
    assert stats.status == Status.CONTENT
    figures = json.loads(stats.payload)
    assert figures["robot_id"] == "Robot1" and figures["transport"] == "coap"
    assert figures["server"]["messages_received"] > 0
    cbor_stats = await ask(Method.GET, "/robot/stats")
    assert cbor2.loads(cbor_stats.payload)["robot_id"] == "Robot1"


async def test_a_robot_keeps_its_latest_decisions_and_posts_only() -> None:
    """A robot runs whole shifts: what it keeps per task is bounded (the decision
    listing of ``GET /tasks``, the posts whose repeat it recognises)."""
    robot = await Robot.start(solo_config(free_udp_port()), bounds=RobotBounds(decisions_kept=3, posts_remembered=2))
    client = await open_client("coap")
    try:
        ask = Asker(client, robot.config.bind)
        for seq in range(1, 6):
            assert (await ask.post_task(seq, "Gucci_bag_14")).status == Status.CHANGED
        async with asyncio.timeout(PATIENCE_S):
            while not robot.controller.log or robot.controller.log[-1].seq < 5:
                await asyncio.sleep(0.05)
        listed = json.loads((await ask(Method.GET, "/tasks", accept=ContentFormat.JSON)).payload)
        assert [d["seq"] for d in listed] == [3, 4, 5]
        assert (await ask.post_task(5, "Gucci_bag_14")).status == Status.CHANGED  # a repeat of the latest
        forgotten = await ask.post_task(1, "Gucci_bag_14")
        assert forgotten.status == Status.CONFLICT and "expected task 6" in forgotten.text()
    finally:
        await client.aclose()
        await robot.aclose()
