"""Write concern between robot processes: a writable team of three, each
robot with its data folder (the Location module on Robot1 and Robot3).
``coapkb update --ack`` prints the level reached; ``all`` asked while
Robot3 is killed is answered 5.04 naming what was reached, the write stays
on Robot1, and the restarted Robot3 catches up with it."""

from __future__ import annotations

import asyncio
import re
import signal
from pathlib import Path

import pytest
from support import coapkb
from writable_team import PREFIX, SPEC, labels, start, stop_all, write_configs

from coapkb.kb.client import KBClient
from coapkb.transport import open_client


def _insert(label: str) -> str:
    return PREFIX + f'INSERT DATA {{ loc:{label} loc:written "{label}" }}'


@pytest.mark.timeout(240)
async def test_all_asked_with_a_holder_down_says_what_was_reached(tmp_path: Path) -> None:
    endpoints, configs = write_configs(tmp_path)
    procs: dict[str, asyncio.subprocess.Process] = {}
    client = await open_client("coap")
    kb = KBClient(client, timeout=20)
    robot1 = str(endpoints["Robot1"])
    try:
        started = await asyncio.gather(*(start(configs[r], r) for r in SPEC.robot_ids))
        procs.update(zip(SPEC.robot_ids, started))

        local = await coapkb("update", "--ack", "local", robot1, _insert("first"))
        assert local.code == 0, local.stderr
        assert re.fullmatch(r"version [0-9a-f]+: removed 0, added 1; ack local \(1 of 2 holders\)\n", local.stdout), local
        both = await coapkb("update", "--ack", "all", robot1, _insert("second"))
        assert both.code == 0, both.stderr
        assert both.stdout.endswith("; ack all (2 of 2 holders)\n"), both

        procs["Robot3"].send_signal(signal.SIGKILL)
        await procs.pop("Robot3").wait()
        short = await coapkb("update", "--ack", "all", robot1, _insert("late"))
        assert short.code == 3 and short.stdout == "", short
        [line] = short.stderr.splitlines()  # one line, no traceback
        assert re.fullmatch(
            rf"coapkb: {re.escape(robot1)} answered 5\.04: ack local \(1 of 2 holders\), asked all: written here, "
            r"version [0-9a-f]+, kept on disk; Robot3 unreachable or refused it; it spreads to them when "
            r"they answer: do not send it again", line), line
        assert "late" in await labels(kb, endpoints["Robot1"])  # not undone

        bad = await coapkb("update", "--ack", "most", robot1, _insert("never"))
        assert bad.code == 2 and len(bad.stderr.splitlines()) == 1 and "--ack" in bad.stderr, bad

        procs["Robot3"] = await start(configs["Robot3"], "Robot3")

        async def caught_up() -> None:
            while "late" not in await labels(kb, endpoints["Robot3"]):
                await asyncio.sleep(0.3)

        await asyncio.wait_for(caught_up(), 30)
        assert await labels(kb, endpoints["Robot3"]) == await labels(kb, endpoints["Robot1"]) == {
            "first", "second", "late"}
    finally:
        await client.aclose()
        await stop_all(procs)
