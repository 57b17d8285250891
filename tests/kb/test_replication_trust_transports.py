"""Only holders replicate, over every transport that can be secured: the
sender of ``POST /kb/sync`` is the member its security layer authenticated
(OSCORE/EDHOC, CurveZMQ, mTLS), never a name in the payload.  A robot that
does not hold the module is refused 4.03 and nothing changes; a holder's
own write is taken."""

from __future__ import annotations

import random
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from rdflib import Literal, URIRef
from support import ONTOLOGIES

from coapkb.kb.live import LiveKB, wall_ms
from coapkb.kb.replication import Holder, Replicator
from coapkb.kb.resources import KBResources
from coapkb.kb.store import KnowledgeBase
from coapkb.model.deltas import CausalContext, Delta, Dot, Stamp
from coapkb.security import generate_team, load_identity
from coapkb.security.keys import default_members
from coapkb.security.mechanisms import client_security, server_security
from coapkb.transport import open_client, serve
from coapkb.transport.base import ClientTransport, Endpoint, PeerUnreachable, ServerTransport, TransportError
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status
from coapkb.transport.registry import secured_schemes
from coapkb.transport.router import Router
from coapkb.wire.sync import SyncMessage, encode_sync

LOC = "http://www.tcs.org/2018/Location#"
ANSWER_S = 15.0


class Nowhere(ClientTransport):
    """The served robot's own client: its pushes to Robot3 go nowhere."""

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        raise PeerUnreachable(f"{peer} is not running in this test")

    def observe(self, peer: Endpoint, request: Request):  # type: ignore[no-untyped-def]
        raise NotImplementedError

    async def aclose(self) -> None:
        pass


@dataclass
class Served:
    live: LiveKB
    replicator: Replicator
    server: ServerTransport
    keys: Path


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> Path:
    team = tmp_path_factory.mktemp("team") / "keys"
    generate_team(team, default_members(3))
    return team


@pytest.fixture(params=secured_schemes())
async def robot1(request: pytest.FixtureRequest, keys: Path) -> AsyncIterator[Served]:
    """Robot1 holding Location with Robot3 (Robot2 holds none of it), behind
    the team's access policy over ``scheme``."""
    scheme = request.param
    live = LiveKB(KnowledgeBase.load([ONTOLOGIES / "Location.owl"]), "Robot1.7", wall_ms=wall_ms,
                  holders={"Location": ["Robot1", "Robot3"], "Object": ["Robot1", "Robot2"],
                           "Capability": ["Robot2", "Robot3"]})
    replicator = Replicator(live, Nowhere(), [Holder("Robot3", Endpoint(scheme, "127.0.0.1", 9), ("Location",))],
                            rng=random.Random(1))
    router = Router()
    KBResources(live, replicator=replicator).mount(router)
    server = await serve(router, Endpoint(scheme, "127.0.0.1", 0),
                         security=server_security(scheme, load_identity(keys, "Robot1")))
    try:
        yield Served(live, replicator, server, keys)
    finally:
        await replicator.aclose()
        await server.aclose()


async def _sync_as(member: str, robot: Served, deltas: list[Delta], forward: bool = False) -> Response:
    endpoint = robot.server.endpoint
    security = client_security(endpoint.scheme, load_identity(robot.keys, member), {endpoint.hostport: "Robot1"})
    client = await open_client(endpoint.scheme, security=security)
    message = SyncMessage("Location", CausalContext(), deltas, forward=forward)
    try:
        return await client.request(endpoint, Request(Method.POST, "/kb/sync", payload=encode_sync(message),
                                                      content_format=ContentFormat.CBOR), timeout=ANSWER_S)
    finally:
        await client.aclose()


def _note(writer: str, seq: int, text: str) -> Delta:
    return Delta(Dot(writer, seq), Stamp(wall_ms(), 0, writer), ((URIRef(LOC + "X"), URIRef(LOC + "note"),
                                                                  Literal(text)),))


@pytest.mark.timeout(120)
async def test_a_non_holder_is_refused_and_a_holder_taken(robot1: Served) -> None:
    replica = robot1.live.replicas["Location"]
    etag = robot1.live.etag
    # Robot2 holds no Location: a made-up writer, Robot1's own next dot, passed on or not.
    for delta, forward in ((_note("Mallory.1", 1, "forged"), True), (_note("Robot1.7", 1, "forged"), False)):
        answer = await _sync_as("Robot2", robot1, [delta], forward)
        assert answer.status == Status.FORBIDDEN, answer
        assert answer.text() == "Robot2 does not hold the Location module: only its holders replicate it"
    try:
        feeder = await _sync_as("feeder", robot1, [_note("feeder.1", 1, "forged")])
    except TransportError:
        pass  # Zenoh's own access control drops it: no answer
    else:
        assert feeder.status == Status.FORBIDDEN  # the policy: robots only
    assert robot1.live.etag == etag and not replica.context.vv and not replica.entries and not replica.journal
    assert robot1.replicator.stats.forbidden == 2

    # A holder's own write is taken; one naming Robot2 as its writer is not.
    forged = await _sync_as("Robot3", robot1, [_note("Robot2.5", 1, "forged")])
    assert forged.status == Status.FORBIDDEN and "Robot2 does not hold" in forged.text()
    taken = await _sync_as("Robot3", robot1, [_note("Robot3.4", 1, "real")])
    assert taken.status == Status.CHANGED, taken
    assert replica.context.vv == {"Robot3.4": 1} and robot1.live.etag != etag
