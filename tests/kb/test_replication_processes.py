"""Replication between robots as separate OS processes, under OSCORE: two
clusters of three (each module on two robots of a cluster, and passed on to
the next cluster), writes by the operator's ``coapkb update``, a robot
killed and started again that catches up."""

from __future__ import annotations

import asyncio
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import cbor2
import pytest
from support import ROOT, coapkb, free_udp_port

from coapkb.config import dump_config
from coapkb.harness.team import TeamSpec, robot_configs
from coapkb.security import generate_team, load_identity
from coapkb.security.coap import ClientSecurity
from coapkb.security.keys import default_members
from coapkb.security.settings import SecurityConfig
from coapkb.transport import open_client
from coapkb.transport.base import Endpoint
from coapkb.transport.messages import Method, Request

LOC = "http://www.tcs.org/2018/Location#"
MOVE = (f"PREFIX loc: <{LOC}> DELETE {{{{ loc:Robot1 loc:Robot_aisle_no ?a }}}} "
        "INSERT {{ loc:Robot1 loc:Robot_aisle_no {aisle} }} WHERE {{ loc:Robot1 loc:Robot_aisle_no ?a }}")


class Agents:
    def __init__(self, configs: dict[str, Path]) -> None:
        self.configs = configs
        self.procs: dict[str, asyncio.subprocess.Process] = {}

    async def start(self, robot: str) -> None:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "coapkb", "agent", "--config", str(self.configs[robot]),
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, cwd=ROOT,
        )
        assert proc.stdout is not None
        line = (await asyncio.wait_for(proc.stdout.readline(), 60)).decode()
        assert line.startswith(f"robot {robot} ready"), line + ((await proc.stderr.read()).decode() if proc.stderr else "")
        self.procs[robot] = proc

    async def kill(self, robot: str) -> None:
        proc = self.procs.pop(robot)
        proc.kill()
        await proc.wait()

    async def aclose(self) -> None:
        for robot in list(self.procs):
            proc = self.procs.pop(robot)
            proc.terminate()
            try:
                await asyncio.wait_for(proc.wait(), 10)
            except TimeoutError:
                proc.kill()
                await proc.wait()


@pytest.fixture
async def team(tmp_path: Path) -> AsyncIterator[tuple[Agents, dict[str, Endpoint], Path]]:
    keys = tmp_path / "keys"
    generate_team(keys, default_members(6))
    spec = TeamSpec(robots=6, kb_writable=True)
    endpoints = {r: Endpoint("coap", "127.0.0.1", free_udp_port()) for r in spec.robot_ids}
    paths = {}
    for robot, config in robot_configs(spec, endpoints, security=SecurityConfig(keys)).items():
        paths[robot] = tmp_path / f"{robot}.toml"
        paths[robot].write_text(dump_config(config), encoding="utf-8")
    agents = Agents(paths)
    try:
        await asyncio.gather(*(agents.start(r) for r in spec.robot_ids))
        yield agents, endpoints, keys
    finally:
        await agents.aclose()


async def _versions(endpoints: dict[str, Endpoint], keys: Path, robots: list[str]) -> dict[str, str]:
    """Each robot's version of the Location module (``GET /kb``)."""
    client = await open_client("coap", security=ClientSecurity(load_identity(keys, "operator")))
    try:
        versions = {}
        for robot in robots:
            response = await client.request(endpoints[robot], Request(Method.GET, "/kb"), timeout=20)
            versions[robot] = cbor2.loads(response.payload)["versions"]["Location"]
        return versions
    finally:
        await client.aclose()


async def _converged(endpoints: dict[str, Endpoint], keys: Path, robots: list[str], timeout: float = 40) -> str:
    async def wait() -> str:
        while True:
            versions = await _versions(endpoints, keys, robots)
            if len(set(versions.values())) == 1:
                return next(iter(versions.values()))
            await asyncio.sleep(0.5)

    return await asyncio.wait_for(wait(), timeout)


@pytest.mark.timeout(180)
async def test_writes_reach_every_holder_in_both_clusters_and_a_restarted_robot(team) -> None:
    agents, endpoints, keys = team
    # Location lives on Robot1 and Robot3 (cluster 1), Robot4 and Robot6 (cluster 2).
    holders = ["Robot1", "Robot3", "Robot4", "Robot6"]
    update = await coapkb("update", "--credentials", str(keys), str(endpoints["Robot1"]), MOVE.format(aisle=2))
    assert update.code == 0, update.stderr
    first = await _converged(endpoints, keys, holders)

    await agents.kill("Robot6")
    for aisle in (3, 4, 5):  # written in the other cluster while Robot6 is down
        done = await coapkb("update", "--credentials", str(keys), str(endpoints["Robot4"]), MOVE.format(aisle=aisle))
        assert done.code == 0, done.stderr
    await agents.start("Robot6")
    last = await _converged(endpoints, keys, holders)
    assert last != first

    answer = await coapkb("query", "--credentials", str(keys), str(endpoints["Robot6"]),
                          f"PREFIX loc: <{LOC}> SELECT ?a WHERE {{ loc:Robot1 loc:Robot_aisle_no ?a }}")
    assert answer.code == 0 and answer.stdout.splitlines()[2].strip() == "5", answer

    feeder = await coapkb("update", "--credentials", str(keys), "--identity", "feeder", str(endpoints["Robot1"]),
                          MOVE.format(aisle=9))
    assert feeder.code == 1 and "4.03" in feeder.stderr  # the feeder writes nothing
