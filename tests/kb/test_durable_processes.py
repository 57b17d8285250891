"""Acknowledged writes survive a crash of every holder: a writable team of
three robot processes, each with its data folder; the operator writes N
times to the Location module's two holders, both are killed with SIGKILL
at once and started again on the same folders: every write is there, on
both, and a write after the restart converges."""

from __future__ import annotations

import asyncio
import os
import random
import signal
from pathlib import Path

import pytest
from writable_team import HOLDERS, PREFIX, SPEC, labels, start, stop_all, write_configs

from coapkb.kb.client import KBClient
from coapkb.transport import open_client

WRITES = 20


@pytest.mark.timeout(240)
async def test_every_acknowledged_write_survives_killing_every_holder(tmp_path: Path) -> None:
    endpoints, configs = write_configs(tmp_path)
    procs: dict[str, asyncio.subprocess.Process] = {}
    client = await open_client("coap")
    kb = KBClient(client, timeout=20)
    try:
        started = await asyncio.gather(*(start(configs[r], r) for r in SPEC.robot_ids))
        procs.update(zip(SPEC.robot_ids, started))
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
        restarted = await asyncio.gather(*(start(configs[r], r) for r in HOLDERS))
        procs.update(zip(HOLDERS, restarted))
        expected = {f"w{i}" for i in range(WRITES)}
        for robot in HOLDERS:
            assert await labels(kb, endpoints[robot]) == expected, robot

        # Written on: as the same writer, above its old dots, and it spreads.
        await kb.update(endpoints["Robot1"], PREFIX + 'INSERT DATA { loc:after loc:written "after" }')

        async def spread() -> None:
            while "after" not in await labels(kb, endpoints["Robot3"]):
                await asyncio.sleep(0.3)

        await asyncio.wait_for(spread(), 30)
        assert await labels(kb, endpoints["Robot1"]) == await labels(kb, endpoints["Robot3"]) == expected | {"after"}
    finally:
        await client.aclose()
        await stop_all(procs)
