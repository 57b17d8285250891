"""How many benchmark runs one machine takes at once without disturbing
their timing: the same runs one, two and three at a time.

    sudo .venv/bin/python -m experiments.concurrency                 # 3 robots, 10 tasks, 35 kbit/s, 2 %: ~3 min
    sudo .venv/bin/python -m experiments.concurrency --robots 9 --reps 2

Each level runs the same list (``--systems`` x ``--reps``, the sweep's own
child processes) through ``sweep.sweep`` with ``jobs`` at a time, and writes
every row with its level to ``experiments/results/concurrency.csv``.  It
prints, per level, the wall time of the list and the median completion time
and wire bytes of each system: a level is safe while its completion times
stay within the spread of the one-at-a-time runs (bytes must not move at
all: they do not depend on the CPU).  The answer sets ``--jobs`` and a Dask
worker's ``--resources netns=N`` (docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from pathlib import Path

import pandas as pd

from coapkb.bench.linkemu import available, cleanup_stale
from coapkb.bench.row import read_rows
from experiments import sweep

ROOT = Path(__file__).resolve().parent.parent

OUT = ROOT / "experiments" / "results" / "concurrency.csv"


def main() -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.concurrency",
                                description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robots", type=int, default=3)
    p.add_argument("--tasks", type=int, default=10)
    p.add_argument("--bandwidth", type=float, default=35.0)
    p.add_argument("--loss", type=float, default=2.0)
    p.add_argument("--systems", default="coap-distributed,zmq-distributed,coap-central")
    p.add_argument("--reps", type=int, default=2)
    p.add_argument("--levels", default="1,2,3", help="runs at once to try (comma-separated)")
    p.add_argument("--out", type=Path, default=OUT)
    args = p.parse_args()
    ok, why = available()
    if not ok:
        print(f"concurrency: no kernel link emulation here: {why}", file=sys.stderr)
        return 2
    cleanup_stale()
    systems = [s.strip() for s in args.systems.split(",") if s.strip()]
    runs = [sweep.Run(s, args.robots, args.tasks, args.bandwidth, args.loss, rep)
            for rep in range(args.reps) for s in systems]
    frames = []
    for jobs in (int(j) for j in args.levels.split(",")):
        scratch = args.out.with_suffix(f".j{jobs}.tmp.csv")
        scratch.unlink(missing_ok=True)
        started = time.monotonic()
        asyncio.run(sweep.sweep(runs, scratch, jobs, []))
        wall = time.monotonic() - started
        frame = pd.DataFrame([r.to_dict() for r in read_rows(scratch)]).assign(jobs=jobs, list_wall_s=round(wall, 1))
        scratch.unlink()
        frames.append(frame)
    data = pd.concat(frames, ignore_index=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    data.to_csv(args.out, index=False)
    summary = data.groupby(["jobs", "system"]).agg(
        runs=("ok", "sum"), completion_s=("completion_s", "median"), wire_bytes=("wire_bytes", "median"),
        list_wall_s=("list_wall_s", "first"),
    )
    print(summary.to_string())
    print(f"rows in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
