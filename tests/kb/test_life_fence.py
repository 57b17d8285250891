"""The lives of a robot kept in memory write under one name, and the fence
keeps an earlier life's pushes still on their way from taking the next
life's dots (docs/knowledge.md, section 6).  Three holders of Location
linked in memory, on the event loop's own clock (looptime)."""

from __future__ import annotations

import random
from collections.abc import AsyncIterator
from dataclasses import dataclass, field

import pytest
from memory_links import Links, at
from support import ONTOLOGIES

from coapkb.kb.life_fence import LifeFence
from coapkb.kb.live import LiveKB, wall_ms
from coapkb.kb.replication import Holder, ReplicationSettings, Replicator
from coapkb.kb.store import KnowledgeBase
from coapkb.kb.write_concern import Ack
from coapkb.transport.messages import ContentFormat, Method, Request, Status
from coapkb.wire.sync import Life, SyncMessage, encode_sync

pytestmark = pytest.mark.looptime

LOC = "http://www.tcs.org/2018/Location#"
ROBOTS = ("A", "B", "C")
SETTINGS = ReplicationSettings(sync_every_s=600, request_timeout_s=5, ack_timeout_s=1, read_after_catch_up_s=3)


def _note(text: str) -> str:
    return f'PREFIX loc: <{LOC}> INSERT DATA {{ loc:Shelf9 loc:note "{text}" }}'


@dataclass
class Team:
    robots: dict[str, Replicator] = field(default_factory=dict)
    down: set[str] = field(default_factory=set)
    silent: set[str] = field(default_factory=set)
    boots: dict[str, int] = field(default_factory=dict)

    def start(self, robot: str) -> Replicator:
        """A new process of ``robot``, kept in memory (not caught up yet)."""
        self.boots[robot] = self.boots.get(robot, 0) + 1
        live = LiveKB(KnowledgeBase.load([ONTOLOGIES / "Location.owl"]), f"{robot}.{self.boots[robot]}",
                      wall_ms=wall_ms)
        holders = [Holder(other, at(other), ("Location",)) for other in ROBOTS if other != robot]
        self.robots[robot] = Replicator(live, Links(robot, self.robots, self.down, self.silent), holders,
                                        settings=SETTINGS, rng=random.Random(1))
        return self.robots[robot]

    def shows(self, robot: str, text: str) -> bool:
        ask = f'PREFIX loc: <{LOC}> ASK {{ loc:Shelf9 loc:note "{text}" }}'
        return bool(self.robots[robot].live.query(ask).value)

    def versions(self) -> set[bytes]:
        return {r.live.module_version("Location") for r in self.robots.values()}

    async def write(self, robot: str, text: str) -> None:
        replicator = self.robots[robot]
        reached = await replicator.acknowledge(replicator.live.update(_note(text)), Ack.ALL)
        assert reached.level == Ack.ALL


@pytest.fixture
async def team() -> AsyncIterator[Team]:
    team = Team()
    for robot in ROBOTS:
        team.start(robot)
    for robot in ROBOTS:
        await team.robots[robot].catch_up()
    yield team
    for replicator in team.robots.values():
        await replicator.aclose()


def test_a_life_is_refused_below_the_highest_known() -> None:
    fence = LifeFence()
    assert fence.begin("A") == Life("A", 1)
    fence.learn("Location", {"A": 3, "B": 2})
    assert fence.refusal(Life("A", 2)) == "A's life 2 has ended: its life 3 has started"
    assert fence.refusal(Life("A", 3)) is None and fence.refusal(Life("C", 1)) is None
    fence.raise_to(Life("B", 1))  # an earlier life's question, late: the fence never goes down
    assert fence.highest("B") == 2


async def test_every_life_kept_in_memory_writes_under_one_name(team: Team) -> None:
    assert [team.robots[r].live.writer for r in ROBOTS] == ["A.0", "B.0", "C.0"]
    await team.write("A", "one")
    await team.robots["A"].aclose()
    restarted = team.start("A")
    await restarted.catch_up()
    assert restarted.live.writer == "A.0" and restarted.fence.own == Life("A", 2)
    await team.write("A", "two")
    # One entry for A across its lives, its count going on above the last life's.
    assert restarted.live.replicas["Location"].context.vv == {"A.0": 2}
    assert all(team.shows(r, "one") and team.shows(r, "two") for r in ROBOTS)
    assert len(team.versions()) == 1
    assert {team.robots[r].fence.highest("A") for r in ROBOTS} == {2}


async def test_an_ended_lifes_push_on_its_way_takes_no_dot_of_the_next(team: Team) -> None:
    """Found in the simulator with a name kept across lives and no fence: a
    push held back past its sender's restart took the next life's dot at one
    holder, which then dropped the next life's write as a repeat."""
    old = team.robots["A"]
    await team.write("A", "one")
    written = old.live.update(_note("held back"))  # its push never left before the kill
    held_back = Request(Method.POST, "/kb/sync", payload=encode_sync(SyncMessage(
        "Location", old.live.replicas["Location"].context.copy(), list(written.deltas.values()),
        life=old.fence.own)), content_format=ContentFormat.CBOR, peer="A")
    await old.aclose()
    restarted = team.start("A")
    await restarted.catch_up()
    answer = await team.robots["B"].handle_sync(held_back)
    assert answer.status == Status.FORBIDDEN
    assert answer.text() == "A's life 1 has ended: its life 2 has started"
    await team.write("A", "two")  # the same dot, A.0:2, as the push held back
    assert all(team.shows(r, "two") and not team.shows(r, "held back") for r in ROBOTS)
    assert len(team.versions()) == 1


async def test_a_holder_not_heard_leaves_the_life_its_own_name(team: Team) -> None:
    await team.robots["A"].aclose()
    team.down.add("C")
    restarted = team.start("A")
    await restarted.catch_up()
    assert restarted.live.writer == "A.2" and restarted.fence.own is None
    # C is down: a write reaches B alone.
    reached = await restarted.acknowledge(restarted.live.update(_note("two")), Ack.TWO)
    assert reached.level == Ack.TWO and team.shows("B", "two")


async def test_a_life_that_wrote_before_its_catch_up_keeps_its_own_name(team: Team) -> None:
    await team.robots["A"].aclose()
    restarted = team.start("A")
    restarted.live.update(_note("early"))
    await restarted.catch_up()
    assert restarted.live.writer == "A.2" and restarted.fence.own is None


async def test_a_holder_started_again_learns_the_lives_before_it_takes_theirs(team: Team) -> None:
    a_life_1 = team.robots["A"].fence.own
    await team.robots["A"].aclose()
    await team.start("A").catch_up()  # A's life 2 fenced B and C
    await team.robots["B"].aclose()
    restarted_b = team.start("B")
    team.silent.update({"A", "C"})
    restarted_b.start()  # its catch-up waits for A and C, who do not answer yet
    push = SyncMessage("Location", team.robots["A"].live.replicas["Location"].context.copy(),
                       list(team.robots["A"].live.update(_note("two")).deltas.values()), life=Life("A", 2))
    request = Request(Method.POST, "/kb/sync", payload=encode_sync(push), content_format=ContentFormat.CBOR,
                      peer="A")
    answer = await restarted_b.handle_sync(request)
    assert answer.status == Status.SERVICE_UNAVAILABLE  # it may not know the fence yet
    assert not team.shows("B", "two")
    team.silent.clear()
    await restarted_b.catch_up()
    assert restarted_b.fence.highest("A") == 2  # from A's and C's answers
    assert restarted_b.fence.told == {"Location"}
    ended = SyncMessage("Location", push.context, push.changes, life=a_life_1)
    answer = await restarted_b.handle_sync(Request(Method.POST, "/kb/sync", payload=encode_sync(ended),
                                                   content_format=ContentFormat.CBOR, peer="A"))
    assert answer.status == Status.FORBIDDEN


async def test_a_robot_may_not_send_as_another_robots_life(team: Team) -> None:
    push = SyncMessage("Location", team.robots["A"].live.replicas["Location"].context.copy(), life=Life("A", 9))
    answer = await team.robots["B"].handle_sync(Request(Method.POST, "/kb/sync", payload=encode_sync(push),
                                                        content_format=ContentFormat.CBOR, peer="C"))
    assert answer.status == Status.FORBIDDEN and answer.text() == "C sent a sync as a life of A"
    assert team.robots["B"].fence.highest("A") == 1


async def test_a_holder_still_catching_up_takes_a_lifes_changes_once_an_answer_told_it_the_lives(
        team: Team) -> None:
    """At a team's start every holder catches up at once: a write whose
    pushes they all refused until their catch-ups ended failed (5.04)."""
    await team.robots["B"].aclose()
    restarted_b = team.start("B")
    question = SyncMessage("Location", restarted_b.live.replicas["Location"].context.copy())
    assert await restarted_b.outgoing.exchange(Holder("A", at("A"), ("Location",)), question) is not None
    assert restarted_b.fence.told == {"Location"}  # A's answer told it the lives
    team.silent.add("C")
    restarted_b.start()  # C does not answer, so it goes on catching up
    assert restarted_b.catching_up
    writer = team.robots["A"]
    push = SyncMessage("Location", writer.live.replicas["Location"].context.copy(),
                       list(writer.live.update(_note("two")).deltas.values()), life=writer.fence.own)
    answer = await restarted_b.handle_sync(Request(Method.POST, "/kb/sync", payload=encode_sync(push),
                                                   content_format=ContentFormat.CBOR, peer="A"))
    assert answer.status == Status.CHANGED and team.shows("B", "two")
