"""Robot memory with one KB module vs two (replication 2): VmRSS of each robot process.

Usage::

    .venv/bin/python -m experiments.replication_rss [--transport coap|zmq] [--tasks 20]

Starts a cluster of three robots (real processes on loopback) with replication
1, then 2, reads ``VmRSS`` from ``/proc/PID/status`` once all are up (idle)
and again after feeding ``--tasks`` tasks, and prints one row per robot.
"""

from __future__ import annotations

import argparse
import asyncio
from pathlib import Path

from coapkb.harness.team import Team, TeamSpec, cluster_modules, draw_tasks


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for {pid}")


async def measure(replication: int, transport: str, tasks: list[str]) -> list[tuple[str, str, float, float]]:
    spec = TeamSpec(robots=3, transport=transport, replication=replication)
    async with Team.launch(spec) as team:
        idle = {r: rss_mib(p.pid) for r, p in team.processes.items()}
        await team.run(tasks)
        after = {r: rss_mib(p.pid) for r, p in team.processes.items()}
    return [
        (r, "+".join(cluster_modules(i, spec)), idle[r], after[r]) for i, r in enumerate(spec.robot_ids)
    ]


async def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.replication_rss", description=__doc__.splitlines()[0])
    parser.add_argument("--transport", choices=("coap", "zmq"), default="coap")
    parser.add_argument("--tasks", type=int, default=20)
    args = parser.parse_args()
    tasks = draw_tasks(args.tasks)
    print("| replication | robot | modules | VmRSS idle (MiB) | VmRSS after tasks (MiB) |")
    print("|---|---|---|---|---|")
    for replication in (1, 2):
        for robot, modules, idle, after in await measure(replication, args.transport, tasks):
            print(f"| {replication} | {robot} | {modules} | {idle:.1f} | {after:.1f} |")


if __name__ == "__main__":
    asyncio.run(main())
