"""A team on a machine whose CPU is taken: no false suspicion, no split decision.

A robot runs path planning, localisation and perception beside coapkb, so
its event loop runs late.  Each run starts ``--busy`` processes that spin
for the whole run (one per core of this 2-core machine: both cores
saturated), then a team of ``--robots`` real robot processes on loopback
(CoAP, OSCORE, the default replication of two) takes ``--tasks`` tasks.
Counted per run: robots the feeder declared down, robots that left a
teammate out of a decision (a task decided in an epoch above 0), tasks
unavailable, disagreements, and the worst loop lateness a robot measured
(its ``/robot/stats``).  The kill runs kill one robot (SIGKILL) at
``--kill-at-task`` under the same load: the death must still be found.

    .venv/bin/python -m experiments.busy_cpu                 # 5 runs under load, 1 with a kill
    .venv/bin/python -m experiments.busy_cpu --reps 1 --kill-reps 0 --tasks 20

Writes ``runs.csv`` in ``--out`` (default ``experiments/results/busy_cpu/``)
and prints one line per run.
"""

from __future__ import annotations

import argparse
import asyncio
import csv
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

from coapkb.feeder.record import FateCounts
from coapkb.harness.team import Fault, Team, TeamSpec, draw_tasks

ROOT = Path(__file__).resolve().parent.parent

DEFAULT_OUT = ROOT / "experiments" / "results" / "busy_cpu"
VICTIM = "Robot2"
#: A process that takes a core for as long as it runs.
SPIN = "while True:\n    pass\n"


@dataclass(frozen=True)
class RunRow:
    kind: str  # "load" or "load+kill"
    rep: int
    robots: int
    tasks: int
    busy: int
    completion_s: float
    declared_down: int
    left_out: int
    unavailable: int
    disagreements: int
    errors: int
    fates: str
    killed: str
    detected_after_s: float | None
    lateness_max_s: float
    lateness_p99_s: float
    down_reasons: str


@contextmanager
def busy(n: int) -> Iterator[None]:
    """``n`` processes spinning at this process's priority until the block ends."""
    spinners = [subprocess.Popen([sys.executable, "-c", SPIN]) for _ in range(n)]
    try:
        yield
    finally:
        for spinner in spinners:
            spinner.kill()
        for spinner in spinners:
            spinner.wait()


async def one_run(kind: str, rep: int, args: argparse.Namespace) -> RunRow:
    tasks = draw_tasks(args.tasks, ROOT / "ontologies", seed=rep + 1)
    faults = (Fault("kill", VICTIM, at_task=args.kill_at_task),) if kind == "load+kill" else ()
    spec = TeamSpec(robots=args.robots, faults=faults)
    with busy(args.busy):
        async with Team.launch(spec) as team:
            record = await team.run(tasks)
    fates = FateCounts.of(record.tasks)
    # A robot that left a teammate out decided in a later epoch than 0
    # (a killed robot's exclusion is the one expected).
    left_out = {r for t in record.tasks for r, epoch in t.epochs.items() if epoch > 0}
    lateness = [s.loop_lateness for s in record.robot_stats.values() if s.loop_lateness is not None]
    detected = [f.detected_after_s for f in record.faults if f.action == "kill"]
    return RunRow(
        kind=kind, rep=rep, robots=args.robots, tasks=args.tasks, busy=args.busy,
        completion_s=round(record.completion_s, 2),
        declared_down=len(record.down), left_out=len(left_out),
        unavailable=fates.unavailable, disagreements=fates.disagreements, errors=fates.errors,
        fates=fates.line(), killed=VICTIM if faults else "",
        detected_after_s=detected[0] if detected else None,
        lateness_max_s=max((x.max_s for x in lateness), default=0.0),
        lateness_p99_s=max((x.p99_s for x in lateness), default=0.0),
        down_reasons="; ".join(f"{r}: {why}" for r, why in record.down.items()),
    )


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.busy_cpu", description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=6)
    parser.add_argument("--tasks", type=int, default=80)
    parser.add_argument("--busy", type=int, default=2, help="spinning processes (default 2: both cores)")
    parser.add_argument("--reps", type=int, default=5, help="runs under load, nobody killed")
    parser.add_argument("--kill-reps", type=int, default=1, help="runs under load with one robot killed")
    parser.add_argument("--kill-at-task", type=int, default=10)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    runs_csv = args.out / "runs.csv"
    plan = [("load", rep) for rep in range(args.reps)] + [("load+kill", rep) for rep in range(args.kill_reps)]
    new = not runs_csv.exists()
    with runs_csv.open("a", newline="", encoding="utf-8") as out:
        writer = csv.DictWriter(out, fieldnames=list(RunRow.__dataclass_fields__))
        if new:
            writer.writeheader()
        for kind, rep in plan:
            row = asyncio.run(one_run(kind, rep, args))
            writer.writerow(asdict(row))
            out.flush()
            print(f"{kind:9} rep{rep}: {row.completion_s:6.1f} s, {row.declared_down} declared down, "
                  f"{row.left_out} left a teammate out, {row.unavailable} unavailable, "
                  f"{row.disagreements} disagreements; detected {row.detected_after_s} s; "
                  f"lateness max {row.lateness_max_s:.2f} s, p99 {row.lateness_p99_s:.3f} s; {row.fates}",
                  flush=True)


if __name__ == "__main__":
    main()
