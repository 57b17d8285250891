"""A writable team of three robot processes on loopback, each with its data
folder (the Location module on Robot1 and Robot3): what the tests of
durable writes and of the write concern share."""

from __future__ import annotations

import asyncio
import dataclasses
import sys
from pathlib import Path

from support import ROOT, free_udp_port

from coapkb.config import dump_config
from coapkb.harness.team import TeamSpec, robot_configs
from coapkb.kb.client import KBClient
from coapkb.kb.results import expect_select
from coapkb.transport.base import Endpoint

LOC = "http://www.tcs.org/2018/Location#"
PREFIX = f"PREFIX loc: <{LOC}>\n"
#: Location's holders in a cluster of three (the harness's placement).
HOLDERS = ("Robot1", "Robot3")
SPEC = TeamSpec(robots=3, kb_writable=True)


def write_configs(tmp_path: Path) -> tuple[dict[str, Endpoint], dict[str, Path]]:
    """Each robot's endpoint and TOML (its data folder under ``tmp_path/data``)."""
    endpoints = {r: Endpoint("coap", "127.0.0.1", free_udp_port()) for r in SPEC.robot_ids}
    configs: dict[str, Path] = {}
    for robot, config in robot_configs(SPEC, endpoints).items():
        assert ("Location" in config.team[robot].kbs) == (robot in HOLDERS)
        configs[robot] = tmp_path / f"{robot}.toml"
        configs[robot].write_text(dump_config(dataclasses.replace(config, data_dir=tmp_path / "data" / robot)),
                                  encoding="utf-8")
    return endpoints, configs


async def start(config: Path, robot: str) -> asyncio.subprocess.Process:
    """``coapkb agent`` on ``config``, once it says it is ready."""
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


async def labels(kb: KBClient, endpoint: Endpoint) -> set[str]:
    """The values of ``loc:written`` the robot at ``endpoint`` holds."""
    result = await kb.sparql(endpoint, PREFIX + "SELECT ?v WHERE { ?s loc:written ?v }", timeout=20)
    return {str(row["v"]) for row in expect_select(result, "written").as_dicts()}


async def stop_all(procs: dict[str, asyncio.subprocess.Process]) -> None:
    """SIGTERM every robot, SIGKILL one that has not stopped within 10 s."""
    for proc in procs.values():
        proc.terminate()
    for proc in procs.values():
        try:
            await asyncio.wait_for(proc.wait(), 10)
        except TimeoutError:
            proc.kill()
            await proc.wait()
