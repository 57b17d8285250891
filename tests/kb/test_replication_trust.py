"""Only holders replicate, each under its own name (no transport).

* A robot never reuses a dot: a forged or replayed dot under its writer
  name cannot take the place of its next real write (which was then
  answered 2.04 with a new version and lost on every holder).
* ``/kb/sync`` of a module is taken only from a robot known to hold it, and
  only for writers that are incarnations of holders; a refusal is 4.03 with
  one line and changes nothing.
* A delta refused at the replica's bound is answered 5.03 with Max-Age,
  never 2.04."""

from __future__ import annotations

import asyncio
import random
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace

import pytest
from rdflib import Literal, URIRef
from support import ONTOLOGIES

from coapkb.kb.live import LiveKB, WriteLimits
from coapkb.kb.replica import Replica, ReplicaLimits
from coapkb.kb.replication import Holder, ReplicationSettings, Replicator, writer_robot
from coapkb.kb.store import KnowledgeBase
from coapkb.model.deltas import CausalContext, Delta, Dot, Stamp, WrittenState
from coapkb.model.results import Triple
from coapkb.transport.base import ClientTransport, Endpoint, PeerGone, PeerUnreachable
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status
from coapkb.wire.sync import SyncMessage, decode_sync, encode_sync

LOC = "http://www.tcs.org/2018/Location#"
NOTE = URIRef(LOC + "note")


def note(subject: str, text: str) -> Triple:
    return (URIRef(LOC + subject), NOTE, Literal(text))


def not_base(_: Triple) -> bool:
    return False


# ------------------------------------------------------- dots are never reused


def test_the_forged_next_dot_loss_and_its_fix() -> None:
    """A delta carrying the writer's next dot reached it (and another
    holder) before its next real write.  Counting from its own counter, the
    write took that dot: it was dropped as a duplicate here and at the other
    holder, though answered as written.  Now it takes the next free dot."""
    robot1, robot2 = Replica("Robot1.7"), Replica("Robot2.9")
    first, _ = robot1.write([], [note("A", "first")], 1000, not_base)
    robot2.apply(first, not_base)
    forged = Delta(Dot("Robot1.7", 2), Stamp(1001, 0, "Robot1.7"), (note("A", "forged"),))
    robot1.apply(forged, not_base)
    robot2.apply(forged, not_base)

    # The loss, as it was: the real write numbered from the writer's own count.
    as_before = Delta(Dot("Robot1.7", 2), Stamp(1002, 0, "Robot1.7"), (note("A", "real"),))
    assert not robot1.apply(as_before, not_base) and note("A", "real") not in robot1.entries

    real, effect = robot1.write([], [note("A", "real")], 1002, not_base)
    assert real.dot == Dot("Robot1.7", 3)
    assert note("A", "real") in effect.added and note("A", "real") in robot1.entries
    assert note("A", "real") in robot2.apply(real, not_base).added
    assert robot1.equal_to(robot2)


def test_a_forged_dot_past_a_gap_is_stepped_over_and_the_gap_fills() -> None:
    robot1 = Replica("Robot1.7")
    robot1.write([], [note("A", "1")], 1000, not_base)
    robot1.apply(Delta(Dot("Robot1.7", 4), Stamp(1001, 0, "Robot1.7"), (note("A", "forged"),)), not_base)
    # Two triples fit below the forged dot; the next write of two does not.
    assert robot1.write([], [note("A", "2"), note("A", "3")], 1002, not_base)[0].dot.seq == 2
    three, _ = robot1.write([], [note("A", "4"), note("A", "5")], 1003, not_base)
    assert three.dots == (Dot("Robot1.7", 5), Dot("Robot1.7", 6))
    assert robot1.context.vv == {"Robot1.7": 6} and not robot1.context.cloud  # no gap left behind
    assert robot1.write([], [note("A", "6")], 1004, not_base)[0].dot.seq == 7


def test_a_forged_removal_of_the_next_dot_does_not_hide_the_next_write() -> None:
    robot1 = Replica("Robot1.7")
    robot1.write([], [note("A", "1")], 1000, not_base)
    # A delta removing Robot1's dot 2 before it exists leaves a tombstone.
    robot1.apply(Delta(Dot("Robot2.9", 1), Stamp(1001, 0, "Robot2.9"), removed=(Dot("Robot1.7", 2),)), not_base)
    real, effect = robot1.write([], [note("A", "real")], 1002, not_base)
    assert real.dot.seq == 3 and note("A", "real") in effect.added


def test_a_whole_state_holding_dots_under_the_writers_name_moves_its_count_past_them() -> None:
    robot1, other = Replica("Robot1.7"), Replica("Robot2.9")
    context = CausalContext({"Robot1.7": 5})
    forged = WrittenState(context, {note("A", "forged"): {Dot("Robot1.7", 5): Stamp(1, 0, "Robot1.7")}}, frozenset())
    robot1.join(forged, not_base)
    other.join(forged, not_base)
    real, effect = robot1.write([], [note("A", "real")], 1002, not_base)
    assert real.dot.seq == 6 and note("A", "real") in effect.added
    assert note("A", "real") in other.apply(real, not_base).added


@pytest.mark.parametrize("writer, robot", [
    ("Robot1.123", "Robot1"), ("A.1", "A"), ("my.robot.42", "my.robot"), ("Robot1", "Robot1"),
    ("Robot1.x", "Robot1.x"), (".5", ".5"),
])
def test_a_writer_is_an_incarnation_of_a_robot(writer: str, robot: str) -> None:
    assert writer_robot(writer) == robot


# ------------------------------------------------------------ who replicates


class Recorder(ClientTransport):
    """A client that records what the replicator sends and answers with ``answer``."""

    def __init__(self, answer: Callable[[Endpoint, Request], Response] | None = None) -> None:
        self.sent: list[tuple[Endpoint, Request]] = []
        self.answer = answer

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        self.sent.append((peer, request))
        if self.answer is None:
            raise PeerUnreachable(f"{peer} is not there")
        return self.answer(peer, request)

    def observe(self, peer: Endpoint, request: Request):  # type: ignore[no-untyped-def]
        raise NotImplementedError

    async def aclose(self) -> None:
        pass


#: A cluster as robot.py wires it: Location on Robot1 and Robot3, not Robot2;
#: Robot4 holds it in the next cluster; Robot5 is named nowhere.
CLUSTER = {"Location": ["Robot1", "Robot3"], "Object": ["Robot1", "Robot2"], "Capability": ["Robot2", "Robot3"]}


def ep(port: int) -> Endpoint:
    return Endpoint("coap", "127.0.0.1", port)


def robot1(client: ClientTransport | None = None, *, team: Mapping[str, Sequence[str]] | None = None,
           limits: ReplicaLimits | None = None) -> Replicator:
    live = LiveKB(KnowledgeBase.load([ONTOLOGIES / "Location.owl"]), "Robot1.7", wall_ms=lambda: 1_000,
                  holders=CLUSTER, limits=WriteLimits(replica=limits or ReplicaLimits()))
    holders = [Holder("Robot3", ep(3), ("Location",)), Holder("Robot4", ep(4), ("Location",), remote=True)]
    return Replicator(live, client or Recorder(), holders, settings=ReplicationSettings(sync_every_s=5.0),
                      rng=random.Random(1), team=team)


def push(deltas: Sequence[Delta] | WrittenState | None, peer: str | None, *, forward: bool = False,
         context: CausalContext | None = None) -> Request:
    message = SyncMessage("Location", context or CausalContext(), deltas, forward=forward)
    return Request(Method.POST, "/kb/sync", payload=encode_sync(message), content_format=ContentFormat.CBOR,
                   peer=peer)


def write(writer: str, seq: int, *triples: Triple, removed: tuple[Dot, ...] = ()) -> Delta:
    return Delta(Dot(writer, seq), Stamp(2_000, 0, writer), triples, removed)


def unchanged(replicator: Replicator, etag: bytes) -> bool:
    replica = replicator.live.replicas["Location"]
    return (replicator.live.etag == etag and not replica.context.vv and not replica.entries
            and not replica.tombstones and not replica.journal and not replicator.known)


async def test_a_robot_that_does_not_hold_the_module_is_refused_and_nothing_changes() -> None:
    """The report: with Robot2's credential (Robot2 holds no Location), a
    push under a made-up writer, and one carrying Robot1's own next dot."""
    client = Recorder()
    replicator = robot1(client)
    etag = replicator.live.etag
    for delta in (write("Mallory.1", 1, note("X", "forged")), write("Robot1.7", 1, note("X", "forged"))):
        for forward in (False, True):
            answer = await replicator.handle_sync(push([delta], "Robot2", forward=forward))
            assert answer.status == Status.FORBIDDEN, answer
            assert answer.text() == "Robot2 does not hold the Location module: only its holders replicate it"
    # A question too: Robot2 never has a reason to ask.
    assert (await replicator.handle_sync(push(None, "Robot2"))).status == Status.FORBIDDEN
    assert unchanged(replicator, etag) and client.sent == []
    assert replicator.stats.forbidden == 5
    # Its next real write is its first.
    written = replicator.live.update(f"PREFIX loc: <{LOC}> INSERT DATA {{ loc:X loc:note 'real' }}")
    assert written.deltas["Location"].dot == Dot("Robot1.7", 1)


async def test_a_robot_its_configuration_does_not_name_may_ask_but_not_send() -> None:
    """Robot5 (another cluster, named nowhere here): its changes are
    refused; its question is a read, answered."""
    replicator = robot1()
    etag = replicator.live.etag
    refused = await replicator.handle_sync(push([write("Robot5.3", 1, note("X", "x"))], "Robot5", forward=True))
    assert refused.status == Status.FORBIDDEN
    assert "Robot5 is not a holder of the Location module that this robot knows" in refused.text()
    asked = await replicator.handle_sync(push(None, "Robot5", context=CausalContext({"Robot5.3": 4})))
    assert asked.status == Status.CHANGED
    assert decode_sync(asked.payload).module == "Location"
    assert unchanged(replicator, etag)  # its context is not kept either


async def test_a_holder_is_refused_a_writer_known_not_to_hold_the_module() -> None:
    replicator = robot1()
    etag = replicator.live.etag
    for message in (
        push([write("Robot2.5", 1, note("X", "x"))], "Robot3"),  # Robot2: in the cluster, no Location
        push([write("Robot3.2", 1, note("X", "x"), removed=(Dot("Robot2.5", 1),))], "Robot3"),
        push(None, "Robot3", context=CausalContext({"Robot2.5": 1})),
        push([write("Robot3.2", 1, note("X", "x"))], "Robot4", context=CausalContext({"Robot2.5": 3}), forward=True),
    ):
        answer = await replicator.handle_sync(message)
        assert answer.status == Status.FORBIDDEN, answer
        assert "written by Robot2.5: Robot2 does not hold the Location module" in answer.text()
    assert unchanged(replicator, etag)


async def test_a_whole_state_with_a_non_holders_dot_is_refused_whole() -> None:
    replicator = robot1()
    etag = replicator.live.etag
    good = {note("X", "a"): {Dot("Robot3.2", 1): Stamp(1, 0, "Robot3.2")}}
    states = [
        WrittenState(CausalContext({"Robot3.2": 1, "Robot2.5": 1}),
                     {**good, note("X", "b"): {Dot("Robot2.5", 1): Stamp(1, 0, "Robot2.5")}}, frozenset()),
        WrittenState(CausalContext({"Robot3.2": 1}), good, frozenset(), frozenset({Dot("Robot2.5", 4)})),
        WrittenState(CausalContext({"Robot3.2": 1}, [Dot("Robot2.5", 9)]), good, frozenset()),
    ]
    for state in states:
        answer = await replicator.handle_sync(push(state, "Robot3"))
        assert answer.status == Status.FORBIDDEN and "Robot2 does not hold" in answer.text(), answer
    assert unchanged(replicator, etag)
    taken = await replicator.handle_sync(push(WrittenState(CausalContext({"Robot3.2": 1}), good, frozenset()),
                                              "Robot3"))
    assert taken.status == Status.CHANGED and note("X", "a") in replicator.live.replicas["Location"].entries


async def test_a_holder_relays_the_writes_of_holders_it_knows_and_of_other_clusters() -> None:
    """Robot4 (the next cluster's holder) forwards its own write, Robot3's,
    and one of Robot6, a holder of its cluster this robot does not know:
    taken on Robot4's word, and passed on to the holders here."""
    client = Recorder()
    replicator = robot1(client)
    deltas = [write("Robot4.1", 1, note("X", "4")), write("Robot3.2", 1, note("X", "3")),
              write("Robot6.8", 1, note("X", "6"))]
    answer = await replicator.handle_sync(push(deltas, "Robot4", forward=True))
    assert answer.status == Status.CHANGED, answer
    entries = replicator.live.replicas["Location"].entries
    assert {note("X", n) for n in "436"} <= set(entries)
    assert ("Location", "Robot4") in replicator.known
    await _settle(replicator)
    assert sorted(e.port for e, _ in client.sent) == [3, 4]


async def test_with_the_teams_list_a_robot_it_does_not_list_holds_nothing() -> None:
    team = {"Location": ["Robot1", "Robot3", "Robot4", "Robot6"]}
    replicator = robot1(team=team)
    etag = replicator.live.etag
    unknown = await replicator.handle_sync(push([write("Robot5.3", 1, note("X", "x"))], "Robot4", forward=True))
    assert unknown.status == Status.FORBIDDEN and "Robot5 does not hold the Location module" in unknown.text()
    assert (await replicator.handle_sync(push(None, "Robot5"))).status == Status.FORBIDDEN
    assert unchanged(replicator, etag)
    listed = await replicator.handle_sync(push([write("Robot6.8", 1, note("X", "6"))], "Robot4", forward=True))
    assert listed.status == Status.CHANGED
    await _settle(replicator)


async def test_an_unprotected_sender_is_not_checked_but_non_holders_writes_are() -> None:
    """No security: nobody was authenticated, so the sender cannot be held
    to anything; a writer known not to hold the module is still refused."""
    replicator = robot1()
    etag = replicator.live.etag
    refused = await replicator.handle_sync(push([write("Robot2.5", 1, note("X", "x"))], None))
    assert refused.status == Status.FORBIDDEN and "Robot2 does not hold" in refused.text()
    assert unchanged(replicator, etag)
    taken = await replicator.handle_sync(push([write("Robot5.3", 1, note("X", "x"))], None))
    assert taken.status == Status.CHANGED


async def test_an_answer_naming_a_non_holders_writer_is_not_taken() -> None:
    """The other way round: a holder asked answers with Robot2's write."""
    def answer(peer: Endpoint, request: Request) -> Response:
        forged = SyncMessage("Location", CausalContext({"Robot2.5": 1}), [write("Robot2.5", 1, note("X", "x"))])
        return Response(Status.CHANGED, encode_sync(forged), ContentFormat.CBOR)

    replicator = robot1(Recorder(answer))
    etag = replicator.live.etag
    await replicator.sync_once()
    # A round asks the next holder when an answer is not taken: both forged here.
    assert unchanged(replicator, etag) and replicator.stats.forbidden == 2


async def test_a_delta_refused_at_the_bound_is_answered_5_03_not_2_04() -> None:
    """Dots past a gap beyond ``cloud_max`` are not taken: the sender must
    not count the write as held here.  The part taken is kept."""
    client = Recorder()
    replicator = robot1(client, limits=ReplicaLimits(cloud_max=2))
    deltas = [write("Robot3.2", 1, note("X", "1")), write("Robot3.2", 5, note("X", "5")),
              write("Robot3.2", 7, note("X", "7"), note("X", "8"))]
    answer = await replicator.handle_sync(push(deltas, "Robot4", forward=True))
    assert answer.status == Status.SERVICE_UNAVAILABLE and answer.max_age == 5, answer
    assert answer.text().startswith("1 of the changes not taken")
    replica = replicator.live.replicas["Location"]
    assert Dot("Robot3.2", 1) in replica.context and Dot("Robot3.2", 7) not in replica.context
    assert replica.refused == 1 and replicator.stats.not_taken == 1
    await _settle(replicator)
    # Only what was taken is passed on.
    passed = {d.dot for _, r in client.sent for d in decode_sync(r.payload).changes or ()}  # type: ignore[union-attr]
    assert passed == {Dot("Robot3.2", 1), Dot("Robot3.2", 5)}


async def _settle(replicator: Replicator) -> None:
    await asyncio.gather(*list(replicator.outgoing.pushes), return_exceptions=True)


class Network(ClientTransport):
    """In memory: a request reaches the replicator at the endpoint's port,
    sent by ``me`` as a security layer would authenticate it."""

    def __init__(self, me: str, robots: dict[int, Replicator]) -> None:
        self.me, self.robots = me, robots

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        return await self.robots[peer.port].handle_sync(replace(request, peer=self.me))

    def observe(self, peer: Endpoint, request: Request):  # type: ignore[no-untyped-def]
        raise NotImplementedError

    async def aclose(self) -> None:
        pass


def ring(team: Mapping[str, Sequence[str]] | None) -> dict[int, Replicator]:
    """Three clusters of one holder each: A1 -> B1 -> C1 -> A1, each
    configured with the next only (as the harness does)."""
    robots: dict[int, Replicator] = {}
    names = ["A1", "B1", "C1"]
    for port, name in enumerate(names):
        nxt = names[(port + 1) % 3]
        live = LiveKB(KnowledgeBase.load([ONTOLOGIES / "Location.owl"]), f"{name}.1", wall_ms=lambda: 1_000,
                      holders={"Location": [name]})
        robots[port] = Replicator(live, Network(name, robots), [Holder(nxt, ep((port + 1) % 3), ("Location",),
                                                                       remote=True)],
                                  rng=random.Random(port), team=team)
    return robots


@pytest.mark.parametrize("listed", [False, True])
async def test_a_ring_of_three_clusters_converges_with_or_without_the_teams_list(listed: bool) -> None:
    """Without the team's list a robot does not know the previous cluster's
    holder: its push is refused, and the write crosses by the questions of
    anti-entropy (each robot asks the next).  With the list it is taken at once."""
    robots = ring({"Location": ["A1", "B1", "C1"]} if listed else None)
    a1 = robots[0]
    written = a1.live.update(f"PREFIX loc: <{LOC}> INSERT DATA {{ loc:X loc:note 'a' }}")
    assert await a1.replicate(written) == (1 if listed else 0)
    await asyncio.gather(*(_settle(r) for r in robots.values()))
    rounds = 0
    while len({r.live.etag for r in robots.values()}) > 1:
        rounds += 1
        assert rounds <= 3, [r.live.replicas["Location"].context for r in robots.values()]
        for robot in robots.values():
            await robot.sync_once()
        await asyncio.gather(*(_settle(r) for r in robots.values()))
    assert rounds == (0 if listed else 2)
    assert (robots[1].stats.forbidden > 0) is not listed  # A1's pushes, refused


class GoneNetwork(Network):
    """:class:`Network` where a robot not in ``robots`` is gone (port unreachable)."""

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        if peer.port not in self.robots:
            raise PeerGone(f"{peer}: nobody listens there")
        return await super().request(peer, request, timeout=timeout)


async def test_a_robot_whose_usual_holders_are_gone_catches_up_from_a_standby() -> None:
    """A1's teammate A2 and its next-cluster holder B1 are killed for good;
    B2, a standby, has a write A1 lacks: the next round fetches it from B2,
    and A1's own write, pushed to nobody alive, reaches B2 the same way.  A
    write is never pushed to a standby."""
    robots: dict[int, Replicator] = {}
    holders = [Holder("A2", ep(1), ("Location",)), Holder("B1", ep(2), ("Location",), remote=True),
               Holder("B2", ep(3), ("Location",), remote=True, standby=True)]
    live = LiveKB(KnowledgeBase.load([ONTOLOGIES / "Location.owl"]), "A1.1", wall_ms=lambda: 1_000)
    robots[0] = a1 = Replicator(live, GoneNetwork("A1", robots), holders, rng=random.Random(0))
    live = LiveKB(KnowledgeBase.load([ONTOLOGIES / "Location.owl"]), "B2.1", wall_ms=lambda: 1_000)
    robots[3] = b2 = Replicator(live, GoneNetwork("B2", robots), [
        Holder("A1", ep(0), ("Location",), remote=True, standby=True)], rng=random.Random(3))
    assert await b2.replicate(b2.live.update(f"PREFIX loc: <{LOC}> INSERT DATA {{ loc:X loc:note 'b2' }}")) == 0
    assert await a1.replicate(a1.live.update(f"PREFIX loc: <{LOC}> INSERT DATA {{ loc:X loc:note 'a1' }}")) == 0
    await _settle(a1)
    assert a1.stats.push_failed == 2  # to A2 and B1, not to the standby
    assert note("X", "a1") not in b2.live.replicas["Location"].entries
    await a1.sync_once()
    await _settle(a1)
    assert a1.live.etag == b2.live.etag
    assert note("X", "b2") in a1.live.replicas["Location"].entries
    assert note("X", "a1") in b2.live.replicas["Location"].entries
