"""Write concern: PATCH ``/kb?ack=local|2|all`` is answered once the write
reached that far, and says how far it reached (in process: the handler, a
replicator per holder, holders that are up, down or silent)."""

from __future__ import annotations

import asyncio
import random
import re
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from memory_links import Links, at
from support import ONTOLOGIES

from coapkb.kb.client import KBClient, QueryFailed, WriteShort
from coapkb.kb.durable import Keeper, open_live
from coapkb.kb.live import LiveKB, wall_ms
from coapkb.kb.named_updates import NamedUpdate
from coapkb.kb.replication import Holder, ReplicationSettings, Replicator
from coapkb.kb.resources import KBResources
from coapkb.kb.store import KnowledgeBase
from coapkb.kb.write_concern import (
    Ack,
    Reached,
    ack_of_query,
    changed_line,
    decode_changed,
    encode_changed,
    parse_ack,
    parse_answer,
    short_line,
)
from coapkb.transport.memory import MemoryNetwork
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status
from coapkb.transport.router import Router

LOC = "http://www.tcs.org/2018/Location#"
OBJ = "http://www.tcs.org/2018/Object#"
INSERT = f"PREFIX loc: <{LOC}> INSERT DATA {{ loc:Shelf9 loc:note %s }}"
WAIT_S = 0.3

# On the in-memory network, on the event loop's own clock (looptime): the
# holders' acknowledgement wait runs out when nothing else can happen, not
# when a busy machine was slow to run a holder that does answer.
pytestmark = pytest.mark.looptime


@dataclass
class Team:
    """Robot A written to; B and C hold what the test says."""

    robots: dict[str, Replicator]
    down: set[str]
    silent: set[str]
    kb: KBClient
    network: MemoryNetwork
    keepers: list[Keeper]

    def live(self, robot: str) -> LiveKB:
        return self.robots[robot].live

    def shows(self, robot: str, note: str) -> bool:
        ask = f'PREFIX loc: <{LOC}> ASK {{ loc:Shelf9 loc:note "{note}" }}'
        return bool(self.live(robot).query(ask).value)  # type: ignore[union-attr]

    async def patch(self, text: str, query: dict[str, str] | None = None) -> Response:
        request = Request(Method.PATCH, "/kb", query or {}, payload=text.encode(), content_format=0)
        return await self.network.client().request(at("A"), request, timeout=30)

    async def aclose(self) -> None:
        for robot in self.robots.values():
            await robot.aclose()
        for keeper in self.keepers:
            keeper.close()

    async def settle(self) -> None:
        for robot in self.robots.values():
            await asyncio.gather(*list(robot.outgoing.pushes), return_exceptions=True)


def _kb(*modules: str) -> KnowledgeBase:
    return KnowledgeBase.load([ONTOLOGIES / f"{m}.owl" for m in modules])


async def _team(holds: dict[str, tuple[str, ...]], tmp_path: Path | None = None) -> Team:
    """Robots holding ``holds``' modules, each knowing the others as holders;
    A served over the in-memory transport (in ``tmp_path`` if given: a data folder)."""
    robots: dict[str, Replicator] = {}
    keepers: list[Keeper] = []
    down: set[str] = set()
    silent: set[str] = set()
    settings = ReplicationSettings(sync_every_s=60, request_timeout_s=60, ack_timeout_s=WAIT_S)
    for name, modules in holds.items():
        if name == "A" and tmp_path is not None:
            live, keeper = open_live(_kb(*modules), "A", 1, tmp_path / "A", wall_ms=wall_ms)
            assert keeper is not None
            keepers.append(keeper)
        else:
            live = LiveKB(_kb(*modules), f"{name}.1", wall_ms=wall_ms)
        holders = [Holder(other, at(other), tuple(m for m in ms if m in modules))
                   for other, ms in holds.items() if other != name and set(ms) & set(modules)]
        robots[name] = Replicator(live, Links(name, robots, down, silent), holders, settings=settings,
                                  rng=random.Random(1))
    router = Router()
    KBResources(robots["A"].live, replicator=robots["A"]).mount(router)
    network = MemoryNetwork()
    await network.serve(router, at("A"))
    return Team(robots, down, silent, KBClient(network.client(), timeout=30), network, keepers)


@pytest.fixture
async def three() -> AsyncIterator[Team]:
    """Location on A, B and C."""
    team = await _team({"A": ("Location",), "B": ("Location",), "C": ("Location",)})
    yield team
    await team.aclose()


# ------------------------------------------------------------------ the option


def test_the_option_parses_exactly_its_three_levels() -> None:
    assert ack_of_query({}) is Ack.TWO  # a request without it: as before
    assert [ack_of_query({"ack": a}) for a in ("local", "2", "all")] == [Ack.LOCAL, Ack.TWO, Ack.ALL]
    for bad in ("", "1", "ALL", "majority", "3", " all"):
        with pytest.raises(ValueError, match="ack takes local, 2 or all, not"):
            ack_of_query({"ack": bad})
    with pytest.raises(ValueError, match=re.escape("one query parameter ack=local|2|all; not 'acks'")):
        ack_of_query({"acks": "all"})
    # The robot takes a write's id beside it (coapkb.kb.write_ids).
    assert ack_of_query({"wid": "a.1"}, {"wid": "WRITER.N"}) is Ack.TWO
    with pytest.raises(ValueError, match=re.escape("the query parameters ack=local|2|all and wid=WRITER.N; not 'w'")):
        ack_of_query({"w": "a.1"}, {"wid": "WRITER.N"})
    assert parse_ack("all").covers(Ack.TWO) and Ack.TWO.covers(Ack.LOCAL) and not Ack.LOCAL.covers(Ack.TWO)


def test_both_answers_read_back() -> None:
    reached = Reached(Ack.TWO, 2, 3, ("C",))
    line = changed_line(1, 1, reached, durable=True)
    assert line == "removed 1, added 1; ack 2 (2 of 3 holders)"
    assert parse_answer(line, short=False) == parse_answer(line, short=False)
    assert parse_answer(line, short=False).reached is Ack.TWO  # type: ignore[union-attr]
    short = short_line(reached, Ack.ALL, bytes.fromhex("0a0b"), durable=False, wait_s=10)
    assert short == ("ack 2 (2 of 3 holders, in memory), asked all: written here, version 0a0b, in memory only "
                     "(no data folder); C did not answer within 10 s; it spreads to them when they answer: "
                     "do not send it again")
    said = parse_answer(short, short=True)
    assert said is not None and (said.reached, said.asked, said.version) == (Ack.TWO, Ack.ALL, b"\x0a\x0b")
    assert parse_answer("removed 1, added 1", short=False) is None  # a robot before write concerns
    assert parse_answer("Robot2 does not answer Robot1 either", short=True) is None


# ------------------------------------------------------------------ the handler


@pytest.mark.parametrize(("query", "reached"), [
    ({"ack": "local"}, "ack local (1 of 3 holders, in memory)"),
    # The strongest level reached is said: in memory both pushes are answered at once.
    ({"ack": "2"}, "ack all (3 of 3 holders, in memory)"),
    ({}, "ack all (3 of 3 holders, in memory)"),  # the default
    ({"ack": "all"}, "ack all (3 of 3 holders, in memory)"),
])
async def test_each_level_is_answered_when_reached(three: Team, query: dict[str, str], reached: str) -> None:
    response = await three.patch(INSERT % '"x"', query)
    assert response.status == Status.CHANGED, response.text()
    assert response.text() == f"removed 0, added 1; {reached}"
    assert response.etag == three.live("A").etag
    await three.settle()  # the pushes not waited for go on
    assert all(three.shows(r, "x") for r in "ABC")


async def test_local_waits_for_no_holder(three: Team) -> None:
    three.silent |= {"B", "C"}
    started = asyncio.get_running_loop().time()
    response = await three.patch(INSERT % '"x"', {"ack": "local"})
    assert response.status == Status.CHANGED and "ack local (1 of 3 holders" in response.text()
    assert asyncio.get_running_loop().time() - started < WAIT_S
    assert three.shows("A", "x")


@pytest.mark.parametrize("query", [{"ack": "2"}, {}])
async def test_two_is_met_with_one_holder_down_or_silent(three: Team, query: dict[str, str]) -> None:
    three.down.add("C")
    response = await three.patch(INSERT % '"x"', query)
    assert response.status == Status.CHANGED and response.text().endswith("ack 2 (2 of 3 holders, in memory)")
    three.down.clear()
    three.silent.add("C")  # answered at B's confirmation, not at the end of the wait
    started = asyncio.get_running_loop().time()
    response = await three.patch(INSERT % '"y"', query)
    assert response.status == Status.CHANGED and response.text().endswith("ack 2 (2 of 3 holders, in memory)")
    assert asyncio.get_running_loop().time() - started < WAIT_S


@pytest.mark.parametrize(("down", "silent", "ack", "reached", "why"), [
    ({"C"}, set(), "all", "ack 2 (2 of 3 holders, in memory)", "C unreachable or refused it"),
    # silent: answered at the end of the wait
    (set(), {"C"}, "all", "ack 2 (2 of 3 holders, in memory)", f"C did not answer within {WAIT_S:g} s"),
    ({"B"}, {"C"}, "2", "ack local (1 of 3 holders, in memory)",
     f"B unreachable or refused it; C did not answer within {WAIT_S:g} s"),
    ({"B", "C"}, set(), "all", "ack local (1 of 3 holders, in memory)", "B, C unreachable or refused it"),
])
async def test_short_of_the_level_asked_is_5_04_and_the_write_stays(
    three: Team, down: set[str], silent: set[str], ack: str, reached: str, why: str
) -> None:
    three.down |= down
    three.silent |= silent
    before = three.live("A").etag
    response = await three.patch(INSERT % '"x"', {"ack": ack})
    assert response.status == Status.GATEWAY_TIMEOUT
    version = three.live("A").etag
    assert version != before and three.shows("A", "x")  # not undone
    assert response.text() == (f"{reached}, asked {ack}: written here, version {version.hex()}, in memory only "
                               f"(no data folder); {why}; it spreads to them when they answer: do not send it again")
    assert response.max_age is None  # no "try again after"
    # It spreads when they answer: here, at their next exchanges.
    three.down.clear()
    three.silent.clear()
    for name in "BC":
        await three.robots[name].catch_up()
    assert three.shows("B", "x") and three.shows("C", "x")


@pytest.mark.parametrize("query", [{"ack": "most"}, {"ack": ""}, {"ak": "all"}])
async def test_a_bad_ack_is_4_00_and_writes_nothing(three: Team, query: dict[str, str]) -> None:
    before = three.live("A").etag
    response = await three.patch(INSERT % '"x"', query)
    assert response.status == Status.BAD_REQUEST
    assert "\n" not in response.text() and re.search(r"ack", response.text())
    assert three.live("A").etag == before and not three.live("A").changed


async def test_every_module_a_write_changes_needs_its_own_second_holder() -> None:
    """A holds Location and Object; B holds Location, C Object.  With C
    down a write to both modules is on a second holder of Location only."""
    team = await _team({"A": ("Location", "Object"), "B": ("Location",), "C": ("Object",)})
    try:
        team.down.add("C")
        both = (f"PREFIX loc: <{LOC}> PREFIX obj: <{OBJ}> "
                'INSERT DATA { loc:Shelf9 loc:note "x" . obj:Box1 obj:note "y" }')
        response = await team.patch(both)
        assert response.status == Status.GATEWAY_TIMEOUT
        assert response.text().startswith("ack local (2 of 3 holders, in memory), asked 2:")
        assert "; C unreachable or refused it;" in response.text()
        only_location = f'PREFIX loc: <{LOC}> INSERT DATA {{ loc:Shelf9 loc:note "z" }}'
        assert (await team.patch(only_location)).text().endswith("ack all (2 of 2 holders, in memory)")
    finally:
        await team.aclose()


async def test_with_a_data_folder_local_is_on_disk(tmp_path: Path) -> None:
    team = await _team({"A": ("Location",), "B": ("Location",)}, tmp_path)
    try:
        assert (await team.patch(INSERT % '"x"', {"ack": "local"})).text() == \
            "removed 0, added 1; ack local (1 of 2 holders)"
        team.down.add("B")
        short = await team.patch(INSERT % '"y"', {"ack": "all"})
        assert short.status == Status.GATEWAY_TIMEOUT
        assert short.text().startswith("ack local (1 of 2 holders), asked all: written here, version ")
        assert ", kept on disk; B unreachable or refused it;" in short.text()
    finally:
        await team.aclose()


async def test_a_lone_robot_and_a_write_that_changes_nothing(three: Team) -> None:
    router = Router()
    live = LiveKB(_kb("Location"), "Z.1", wall_ms=wall_ms)
    KBResources(live).mount(router)  # no replicator: nobody else holds it
    network = MemoryNetwork()
    await network.serve(router, at("Z"))
    request = Request(Method.PATCH, "/kb", {"ack": "all"}, payload=(INSERT % '"x"').encode(), content_format=0)
    first = await network.client().request(at("Z"), request, timeout=10)
    assert first.text() == "removed 0, added 1; ack all (1 of 1 holder, in memory)"
    # The same insert again changes nothing: nothing to pass on.
    assert (await three.patch(INSERT % '"w"')).status == Status.CHANGED
    again = await three.patch(INSERT % '"w"', {"ack": "all"})
    assert again.status == Status.CHANGED and again.text() == "removed 0, added 0; ack all (nothing changed)"


# ------------------------------------------------------------------ the client


async def test_the_client_reads_the_level_and_a_short_write(three: Team) -> None:
    answer = await three.kb.write(at("A"), INSERT % '"x"', ack=Ack.ALL)
    assert answer.reached is Ack.ALL and answer.version == three.live("A").etag
    three.down.add("C")
    with pytest.raises(WriteShort) as short:
        await three.kb.update(at("A"), INSERT % '"y"', ack=Ack.ALL)
    assert (short.value.reached, short.value.asked, short.value.version) == (Ack.TWO, Ack.ALL, three.live("A").etag)
    assert isinstance(short.value, QueryFailed) and short.value.response.status == Status.GATEWAY_TIMEOUT
    assert (await three.kb.write(at("A"), INSERT % '"z"')).reached is Ack.TWO


async def test_a_machine_write_is_answered_in_cbor(three: Team) -> None:
    """A write in CBOR (named updates: a robot's own) asks for its answer in
    CBOR, ``[removed, added, level]``, a sixth of the text's bytes; the
    client reads the level from it as from the text."""
    update = [NamedUpdate("robot-at", ("Robot1", 3, 4, 1000))]
    answer = await three.kb.write(at("A"), update, ack=Ack.LOCAL)
    assert answer.reached is Ack.LOCAL and answer.version == three.live("A").etag
    assert answer.text.startswith("removed ") and answer.text.endswith("; ack local")
    raw = await three.kb.call(at("A"), Request(Method.PATCH, "/kb", {"ack": "all"}, accept=ContentFormat.CBOR,
                                               payload=INSERT.encode() % b'"w"', content_format=ContentFormat.TEXT))
    assert raw.content_format == ContentFormat.CBOR and decode_changed(raw.payload) == (0, 1, Ack.ALL)
    assert len(raw.payload) < len(changed_line(0, 1, Reached(Ack.ALL, 3, 3), durable=False)) / 5
    with pytest.raises(ValueError, match="not a write answer"):
        decode_changed(encode_changed(1, 2, Reached(Ack.TWO))[:-1])

