"""A long shift: one team, an unbounded-looking stream of tasks, batteries and memory over time.

Usage::

    .venv/bin/python -m experiments.long_run [--robots 3] [--tasks 10000] [--time-scale 5000]
        [--every 1000] [--out experiments/results/long_run.csv]

A CoAP team (OSCORE keyed by EDHOC, as ``coapkb team`` runs by default) on
127.0.0.1 is fed ``--tasks`` objects drawn from the shipped Object KB; the
execution runs ``--time-scale`` times faster than the wall clock, so a
shift of simulated hours passes in minutes of wall time.  Every
``--every`` decided tasks, the script records each robot's VmRSS, the fates
so far and how many times each robot has recharged at a dock.  A task
refused because every battery sat at its reserve would show up as
``unassigned`` with the battery reason; the robots recharge instead
(``docs/configuration.md``, the execution and battery fields).
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from coapkb.feeder import FateCounts, TaskRecord
from coapkb.harness.team import Team, TeamSpec, draw_tasks
from experiments.common import rss_mib, write_csv

ROOT = Path(__file__).resolve().parent.parent

RESULTS = ROOT / "experiments" / "results"


@dataclass(frozen=True)
class Sample:
    decided: int
    wall_s: float
    robot: str
    rss_mib: float
    assigned: int
    skipped: int
    unassigned: int
    unassigned_reason: str




async def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m experiments.long_run", description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, default=3)
    parser.add_argument("--tasks", type=int, default=10_000)
    parser.add_argument("--time-scale", type=float, default=5000.0)
    parser.add_argument("--every", type=int, default=1000, help="record every this many decided tasks")
    parser.add_argument("--out", type=Path, default=RESULTS / "long_run.csv")
    args = parser.parse_args()
    tasks = draw_tasks(args.tasks, seed=1)
    spec = TeamSpec(robots=args.robots, time_scale=args.time_scale, task_timeout_s=600.0)
    samples: list[Sample] = []
    decided: list[TaskRecord] = []

    async with Team.launch(spec) as team:
        started = time.monotonic()

        def sample(count: int) -> None:
            fates = FateCounts.of(decided)
            for robot, proc in team.processes.items():
                samples.append(Sample(count, round(time.monotonic() - started, 1), robot, round(rss_mib(proc.pid), 1),
                                      fates.assigned, fates.skipped, fates.unassigned, fates.unassigned_reason or ""))
            print(f"{count:>6} tasks decided, {time.monotonic() - started:7.1f} s: "
                  + ", ".join(f"{s.robot} {s.rss_mib:.1f} MiB" for s in samples[-len(team.processes):])
                  + f"; {fates.line()}", flush=True)

        def progress(record: TaskRecord) -> None:
            decided.append(record)
            if len(decided) % args.every == 0:
                sample(len(decided))

        sample(0)
        record = await team.run(tasks, progress)
        if len(decided) % args.every:
            sample(len(decided))
    fates = FateCounts.of(record.tasks)
    recharges = {r: len(s.recharges) for r, s in record.robot_stats.items()}
    print(f"done: {fates.line()}; recharges {recharges}; completion {record.completion_s:.0f} s")
    write_csv(args.out, [f.name for f in fields(Sample)], (asdict(s) for s in samples))
    first = {s.robot: s.rss_mib for s in samples if s.decided == min(args.every, len(decided))}
    last = {s.robot: s.rss_mib for s in samples if s.decided == len(decided)}
    for robot in sorted(last):
        print(f"{robot}: VmRSS {first[robot]:.1f} MiB at task {min(args.every, len(decided))}, "
              f"{last[robot]:.1f} MiB at task {len(decided)} ({last[robot] - first[robot]:+.1f} MiB)")
    return 0 if fates.unassigned == 0 else 1


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
