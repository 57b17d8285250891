"""The journal a holder answers from: what a peer lacks goes as deltas,
not as the whole written state, even when the peer asks with a context
older than one it sent since.

On a long shift the holders pushed every write and compacted at once on
the context the push's answer carried; a question sent before it (or held
up by retransmissions) then asked for deltas already forgotten, and the
answer was the whole state, 100 kB and more, several times a minute.  Now
compaction goes by the contexts known one anti-entropy round ago."""

from __future__ import annotations

import random

from support import ONTOLOGIES

from coapkb.kb.live import LiveKB
from coapkb.kb.replication import Holder, ReplicationSettings, Replicator
from coapkb.kb.store import KnowledgeBase
from coapkb.model.deltas import CausalContext, Dot
from coapkb.transport.base import ClientTransport, Endpoint
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status
from coapkb.wire.sync import SyncMessage, decode_sync, encode_sync

MOVE = ("PREFIX loc: <http://www.tcs.org/2018/Location#> DELETE { loc:Robot1 loc:Robot_aisle_no ?a } "
        "INSERT { loc:Robot1 loc:Robot_aisle_no %d } WHERE { loc:Robot1 loc:Robot_aisle_no ?a }")


class UpToDatePeer(ClientTransport):
    """Robot3 as Robot1 reaches it: it takes every push and answers with a
    context that holds everything Robot1 has."""

    def __init__(self) -> None:
        self.live: LiveKB | None = None

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        assert self.live is not None
        context = self.live.replicas["Location"].context.copy()
        return Response(Status.CHANGED, encode_sync(SyncMessage("Location", context)), ContentFormat.CBOR)

    def observe(self, peer: Endpoint, request: Request):  # type: ignore[no-untyped-def]
        raise NotImplementedError

    async def aclose(self) -> None:
        pass


def _robot1(sync_every_s: float) -> Replicator:
    client = UpToDatePeer()
    live = LiveKB(KnowledgeBase.load([ONTOLOGIES / "Location.owl"]), "Robot1.7", wall_ms=lambda: 1_000)
    client.live = live
    return Replicator(live, client, [Holder("Robot3", Endpoint("coap", "127.0.0.1", 3), ("Location",))],
                      settings=ReplicationSettings(sync_every_s=sync_every_s), rng=random.Random(1))


def _question(context: CausalContext) -> Request:
    return Request(Method.POST, "/kb/sync", payload=encode_sync(SyncMessage("Location", context)),
                   content_format=ContentFormat.CBOR, peer="Robot3")


async def test_a_question_with_an_older_context_gets_deltas_not_the_whole_state() -> None:
    robot1 = _robot1(sync_every_s=60.0)
    live = robot1.live
    for aisle in (2, 3, 4):
        await robot1.replicate(live.update(MOVE % aisle))  # Robot3 answered each push holding it
    answer = decode_sync((await robot1.handle_sync(_question(CausalContext()))).payload)
    assert isinstance(answer.changes, list)  # the deltas, not a WrittenState
    assert [d.dot for d in answer.changes] == [Dot("Robot1.7", n) for n in (1, 2, 3)]


async def test_the_journal_forgets_what_every_holder_had_a_round_ago() -> None:
    robot1 = _robot1(sync_every_s=60.0)
    journal = robot1.live.replicas["Location"].journal
    await robot1.replicate(robot1.live.update(MOVE % 2))  # Robot3 told it holds the write
    robot1.compact()  # the first round: what Robot3 held before it is all it goes by
    assert len(journal) == 1
    robot1.compact()  # a round later
    assert not journal

def test_a_context_counts_what_another_lacks_exactly() -> None:
    """Not an upper bound: the other's dots past a gap are not counted as
    missing (the bound sent a whole state when the journal held them all)."""
    mine = CausalContext({"A": 5}, [Dot("B", 3)])
    theirs = CausalContext({"A": 2}, [Dot("A", 4)])
    assert mine.count_missing_from(theirs) == len(list(mine.missing_from(theirs))) == 3  # A3, A5, B3
