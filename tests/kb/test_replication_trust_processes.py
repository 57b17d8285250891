"""The reported attack on robot processes under OSCORE: with Robot3's
credential (Robot3 holds Location and Capability, not Object), a sync of
Object to Robot1 under a made-up writer, and one carrying Robot1's own next
dot.  Both are refused 4.03, no holder changes, and the operator's next
write to Robot1 reaches both Object holders."""

from __future__ import annotations

import asyncio
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import cbor2
import pytest
from rdflib import Literal, URIRef
from support import ROOT, coapkb, free_udp_port

from coapkb.config import dump_config
from coapkb.harness.team import TeamSpec, robot_configs
from coapkb.model.deltas import CausalContext, Delta, Dot, Stamp
from coapkb.security import generate_team, load_identity
from coapkb.security.coap import ClientSecurity
from coapkb.security.keys import default_members
from coapkb.security.settings import SecurityConfig
from coapkb.transport import open_client
from coapkb.transport.base import Endpoint
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status
from coapkb.wire.sync import SyncMessage, decode_sync, encode_sync
from coapkb.world.vocabulary import LOCATION_NS, OBJECT_NS

ROBOTS = ["Robot1", "Robot2", "Robot3"]


@pytest.fixture
async def team(tmp_path: Path) -> AsyncIterator[tuple[dict[str, Endpoint], Path]]:
    """Three robots of one cluster: Object on Robot1 and Robot2, Location on
    Robot1 and Robot3, Capability on Robot2 and Robot3."""
    keys = tmp_path / "keys"
    generate_team(keys, default_members(3))
    spec = TeamSpec(robots=3, kb_writable=True)
    endpoints = {r: Endpoint("coap", "127.0.0.1", free_udp_port()) for r in spec.robot_ids}
    procs: list[asyncio.subprocess.Process] = []
    try:
        for robot, config in robot_configs(spec, endpoints, security=SecurityConfig(keys)).items():
            path = tmp_path / f"{robot}.toml"
            path.write_text(dump_config(config), encoding="utf-8")
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "coapkb", "agent", "--config", str(path),
                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL, cwd=ROOT,
            )
            procs.append(proc)
            assert proc.stdout is not None
            line = (await asyncio.wait_for(proc.stdout.readline(), 60)).decode()
            assert line.startswith(f"robot {robot} ready"), line
        yield endpoints, keys
    finally:
        for proc in procs:
            proc.terminate()
        for proc in procs:
            try:
                await asyncio.wait_for(proc.wait(), 10)
            except TimeoutError:
                proc.kill()
                await proc.wait()


async def _as(member: str, keys: Path, endpoint: Endpoint, request: Request) -> Response:
    client = await open_client("coap", security=ClientSecurity(load_identity(keys, member)))
    try:
        return await client.request(endpoint, request, timeout=20)
    finally:
        await client.aclose()


def _sync(module: str, deltas: list[Delta] | None) -> Request:
    message = SyncMessage(module, CausalContext(), deltas)
    return Request(Method.POST, "/kb/sync", payload=encode_sync(message), content_format=ContentFormat.CBOR)


async def _versions(endpoints: dict[str, Endpoint], keys: Path, module: str) -> dict[str, str]:
    versions = {}
    for robot in ("Robot1", "Robot2"):
        answer = await _as("operator", keys, endpoints[robot], Request(Method.GET, "/kb"))
        versions[robot] = cbor2.loads(answer.payload)["versions"][module]
    return versions


@pytest.mark.timeout(180)
async def test_a_forged_sync_from_a_robot_without_the_module_changes_no_holder(team) -> None:
    endpoints, keys = team
    first = await coapkb("update", "--credentials", str(keys), str(endpoints["Robot1"]),
                         f"PREFIX obj: <{OBJECT_NS}> PREFIX loc: <{LOCATION_NS}> "
                         "INSERT DATA { obj:Probe obj:note 'first' . loc:Probe loc:note 'first' }")
    assert first.code == 0, first.stderr
    before = await _versions(endpoints, keys, "Object")
    # Robot3 holds Location: it may ask Robot1 for it, and learns Robot1's writer name there.
    asked = await _as("Robot3", keys, endpoints["Robot1"], _sync("Location", None))
    writer = next(w for w in decode_sync(asked.payload).context.vv if w.startswith("Robot1."))

    forged = (OBJECT_NS + "Probe", OBJECT_NS + "note")
    for dot in (Dot("Mallory.1", 1), Dot(writer, 2)):
        delta = Delta(dot, Stamp(1, 0, dot.writer), ((URIRef(forged[0]), URIRef(forged[1]), Literal("forged")),))
        answer = await _as("Robot3", keys, endpoints["Robot1"], _sync("Object", [delta]))
        assert answer.status == Status.FORBIDDEN, answer
        assert answer.text() == "Robot3 does not hold the Object module: only its holders replicate it"
    assert await _versions(endpoints, keys, "Object") == before

    real = await coapkb("update", "--credentials", str(keys), str(endpoints["Robot1"]),
                        f"PREFIX obj: <{OBJECT_NS}> INSERT DATA {{ obj:Probe obj:note 'real' }}")
    assert real.code == 0, real.stderr

    async def converged() -> None:
        while len(set((await _versions(endpoints, keys, "Object")).values())) > 1:
            await asyncio.sleep(0.5)

    await asyncio.wait_for(converged(), 40)
    for robot in ("Robot1", "Robot2"):
        notes = await coapkb("query", "--credentials", str(keys), str(endpoints[robot]),
                             f"PREFIX obj: <{OBJECT_NS}> SELECT ?n WHERE {{ obj:Probe obj:note ?n }} ORDER BY ?n")
        assert notes.code == 0, notes
        assert "real" in notes.stdout and "forged" not in notes.stdout, (robot, notes.stdout)
