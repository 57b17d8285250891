"""Robots killed mid-run on slow lossy links: what replication and liveness
cost, how fast a death is detected, and what happens to every task.

Each cell is one ``coapkb bench`` run (real processes, each robot in its own
network namespace behind the emulated link), for CoAP and ZeroMQ alike:

* ``r1``: the seed's set-up, one holder per KB module, nobody killed;
* ``r2``: every module on two robots of a cluster, nobody killed (the extra
  bytes against ``r1`` are what replication and liveness cost when nothing
  fails);
* ``r2-kill1``: ``r2`` with Robot2 killed (SIGKILL) ``--kill-at`` seconds in;
* ``r2-kill2``: ``r2`` with Robot1 and Robot2 killed, the two holders of the
  Object KB in cluster 1: the tasks that need it are reported unavailable.

    sudo .venv/bin/python -m experiments.faults                      # 6 and 9 robots, 35 kbit/s, 10 % (~15 min)
    sudo .venv/bin/python -m experiments.faults --robots 6 --reps 1
    .venv/bin/python -m experiments.faults --report-only

Writes ``runs.csv`` (one ``BenchRow`` per run, the bench's own schema) and
``table.md`` in ``--out`` (default ``experiments/results/faults/``).
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from coapkb.bench import run as bench
from coapkb.bench.row import BenchRow, append_rows, read_rows
from coapkb.bench.run import retransmission_label
from coapkb.harness.team import Fault
from experiments.common import prepare_link_emulation

ROOT = Path(__file__).resolve().parent.parent

DEFAULT_OUT = ROOT / "experiments" / "results" / "faults"
SYSTEMS = ("coap-distributed", "zmq-distributed")


@dataclass(frozen=True)
class Variant:
    name: str
    replication: int
    victims: tuple[str, ...]


VARIANTS = (
    Variant("r1", 1, ()),
    Variant("r2", 2, ()),
    Variant("r2-kill1", 2, ("Robot2",)),
    Variant("r2-kill2", 2, ("Robot1", "Robot2")),
)


def variant_of(replication: int, faults: str) -> str:
    victims = tuple(f.split("@")[0] for f in faults.split("+") if f)
    return next(v.name for v in VARIANTS if (v.replication, v.victims) == (replication, victims))


async def run_matrix(args: argparse.Namespace, runs_csv: Path) -> None:
    done = {row.key() for row in read_rows(runs_csv)}
    for rep in range(args.reps):
        for robots in args.robots:
            for variant in VARIANTS:
                for system in SYSTEMS:
                    faults = [Fault("kill", victim, args.kill_at) for victim in variant.victims]
                    key = BenchRow(system=system, robots=robots, tasks=args.tasks, bandwidth_kbps=args.bandwidth,
                                   loss_pct=args.loss, rep=rep, retransmission_profile=retransmission_label(system),
                                   replication=variant.replication,
                                   faults="+".join(f"{f.robot}@{f.at_s:g}" for f in faults)).key()
                    if key in done:
                        continue
                    row = await bench.run_once(system, robots, args.tasks, args.bandwidth, args.loss, rep,
                                               replication=variant.replication, faults=faults)
                    append_rows(runs_csv, [row])
                    print(f"{variant.name:9} {bench.format_row(row)}", flush=True)


def report(out: Path) -> str:
    rows = read_rows(out / "runs.csv")
    if not rows:
        return "no runs yet"
    t = pd.DataFrame([r.to_dict() for r in rows])
    t["variant"] = [variant_of(r, f) for r, f in zip(t.replication, t.faults)]
    cells = (
        t.groupby(["robots", "system", "variant"], sort=True)
        .agg(runs=("ok", "size"), ok=("ok", "sum"), completion_s=("completion_s", "median"),
             wire_bytes=("wire_bytes", "median"), detected_s=("fault_detected_s", "median"),
             reassigned=("tasks_reassigned", "median"), unavailable=("tasks_unavailable", "median"),
             agreed=("tasks_agreed", "median"))
        .reset_index()
    )
    base = cells[cells.variant == "r1"].set_index(["robots", "system"])["wire_bytes"]
    cells["bytes_vs_r1"] = [
        round(w / base.get((r, s)), 2) if (r, s) in base.index and pd.notna(w) else None
        for r, s, w in zip(cells.robots, cells.system, cells.wire_bytes)
    ]
    link = f"{rows[0].bandwidth_kbps:g} kbit/s, {rows[0].loss_pct:g} % loss, {rows[0].tasks} tasks"
    lines = [f"# Robots killed mid-run ({link})", "",
             "Medians over the runs of each cell; `bytes_vs_r1`: wire bytes against the same team with one "
             "holder per module and nobody killed.", "",
             cells.to_markdown(index=False, floatfmt="g"), ""]
    return "\n".join(lines)


async def amain(args: argparse.Namespace) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    if not args.report_only:
        why = prepare_link_emulation()
        if why is not None:
            print(f"faults: no kernel link emulation here: {why}", file=sys.stderr)
            return 2
        await run_matrix(args, out / "runs.csv")
    text = report(out)
    (out / "table.md").write_text(text + "\n")
    print(text)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m experiments.faults",
                                description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robots", type=int, nargs="+", default=[6, 9])
    p.add_argument("--tasks", type=int, default=20)
    p.add_argument("--bandwidth", type=float, default=35.0, metavar="KBPS")
    p.add_argument("--loss", type=float, default=10.0, metavar="PCT")
    p.add_argument("--kill-at", type=float, default=2.0, metavar="S", help="seconds into the run (default 2)")
    p.add_argument("--reps", type=int, default=1)
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    p.add_argument("--report-only", action="store_true")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    return asyncio.run(amain(build_parser().parse_args(argv)))


if __name__ == "__main__":
    raise SystemExit(main())
