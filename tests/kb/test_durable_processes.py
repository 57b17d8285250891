"""Acknowledged writes survive a crash of every holder: a writable team of
three robot processes, each with its data folder; the operator writes N
times to the Location module's two holders, both are killed with SIGKILL
at once and started again on the same folders: every write is there, on
both, and a write after the restart converges."""

from __future__ import annotations

import asyncio
import dataclasses
import os
import random
import signal
import sys
from pathlib import Path

import pytest
from support import ROOT, free_udp_port

from coapkb.config import dump_config
from coapkb.harness.team import TeamSpec, robot_configs
from coapkb.kb.client import KBClient
from coapkb.kb.results import expect_select
from coapkb.transport import open_client
from coapkb.transport.base import Endpoint

LOC = "http://www.tcs.org/2018/Location#"
PREFIX = f"PREFIX loc: <{LOC}>\n"
WRITES = 20
#: Location's holders in a cluster of three (the harness's placement).
HOLDERS = ("Robot1", "Robot3")


async def _start(config: Path, robot: str) -> asyncio.subprocess.Process:
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "coapkb", "agent", "--config", str(config),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, cwd=ROOT,
    )
    assert proc.stdout is not None and proc.stderr is not None
    line = (await asyncio.wait_for(proc.stdout.readline(), 90)).decode()
    if not line.startswith(f"robot {robot} ready"):
        proc.kill()
        raise AssertionError(line + (await proc.stderr.read()).decode())
    return proc


async def _labels(kb: KBClient, endpoint: Endpoint) -> set[str]:
    result = await kb.sparql(endpoint, PREFIX + "SELECT ?v WHERE { ?s loc:written ?v }", timeout=20)
    return {str(row["v"]) for row in expect_select(result, "written").as_dicts()}


@pytest.mark.timeout(240)
async def test_every_acknowledged_write_survives_killing_every_holder(tmp_path: Path) -> None:
    spec = TeamSpec(robots=3, kb_writable=True)
    endpoints = {r: Endpoint("coap", "127.0.0.1", free_udp_port()) for r in spec.robot_ids}
    configs: dict[str, Path] = {}
    for robot, config in robot_configs(spec, endpoints).items():
        assert ("Location" in config.team[robot].kbs) == (robot in HOLDERS)
        configs[robot] = tmp_path / f"{robot}.toml"
        configs[robot].write_text(dump_config(dataclasses.replace(config, data_dir=tmp_path / "data" / robot)),
                                  encoding="utf-8")
    procs: dict[str, asyncio.subprocess.Process] = {}
    client = await open_client("coap")
    kb = KBClient(client, timeout=20)
    try:
        started = await asyncio.gather(*(_start(configs[r], r) for r in spec.robot_ids))
        procs.update(zip(spec.robot_ids, started))
        rng = random.Random(5)
        for i in range(WRITES):
            # Each answered 2.04: acknowledged.
            await kb.update(endpoints[rng.choice(HOLDERS)], PREFIX + f'INSERT DATA {{ loc:w{i} loc:written "w{i}" }}')
        for robot in HOLDERS:  # every holder at once, no time to pass anything on
            procs[robot].send_signal(signal.SIGKILL)
        for robot in HOLDERS:
            await procs.pop(robot).wait()
        for robot in HOLDERS:
            assert sorted(os.listdir(tmp_path / "data" / robot)) == [".gitignore", "journal.0", "lock"]
        restarted = await asyncio.gather(*(_start(configs[r], r) for r in HOLDERS))
        procs.update(zip(HOLDERS, restarted))
        expected = {f"w{i}" for i in range(WRITES)}
        for robot in HOLDERS:
            assert await _labels(kb, endpoints[robot]) == expected, robot

        # Written on: as the same writer, above its old dots, and it spreads.
        await kb.update(endpoints["Robot1"], PREFIX + 'INSERT DATA { loc:after loc:written "after" }')

        async def spread() -> None:
            while "after" not in await _labels(kb, endpoints["Robot3"]):
                await asyncio.sleep(0.3)

        await asyncio.wait_for(spread(), 30)
        assert await _labels(kb, endpoints["Robot1"]) == await _labels(kb, endpoints["Robot3"]) == expected | {"after"}
    finally:
        await client.aclose()
        for proc in procs.values():
            proc.terminate()
        for proc in procs.values():
            try:
                await asyncio.wait_for(proc.wait(), 10)
            except TimeoutError:
                proc.kill()
                await proc.wait()
