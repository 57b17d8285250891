"""The spread of repeated runs of one cell: is there a long tail?

    sudo .venv/bin/python -m coapkb bench --robots 3 --tasks 10 --bandwidth 35 --loss 20 \
        --systems coap-distributed --reps 10 --out experiments/results/tail/after.csv
    .venv/bin/python -m experiments.spread experiments/results/tail/after.csv [more.csv ...]

For every cell (system, robots, tasks, bandwidth, loss, security) of the
CSVs, one line per run (completion, coordination, query p99, wire bytes per
task) and a summary: the median, the slowest run against the median
(completion), the worst query p99 and the median wire bytes per task.  A
median hides a run that takes three times the others; this shows it.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

from coapkb.bench.run import BenchRow, read_rows

ROOT = Path(__file__).resolve().parent.parent


def cell(row: BenchRow) -> tuple[str, int, int, float, float, str]:
    return (row.system, row.robots, row.tasks, row.bandwidth_kbps, row.loss_pct, row.security)


def summary(rows: Sequence[BenchRow]) -> dict[str, float]:
    """Median completion, slowest over median, worst query p99 (s), median wire bytes per task."""
    completion = [r.completion_s for r in rows]
    median = statistics.median(completion)
    return {
        "runs": len(rows),
        "completion_median_s": median,
        "slowest_over_median": max(completion) / median,
        "query_p99_max_s": max(r.query_p99_ms for r in rows) / 1000,
        "wire_bytes_per_task": statistics.median(r.wire_bytes / r.tasks for r in rows),
    }


def report(rows: Sequence[tuple[str, BenchRow]]) -> list[str]:
    """``rows``: (label, row) pairs; runs of one cell under different labels
    (two CSVs: before and after a change) are summarised apart."""
    cells: dict[tuple, list[BenchRow]] = defaultdict(list)
    for label, row in rows:
        if row.ok:
            cells[(label, *cell(row))].append(row)
    lines: list[str] = []
    for key, runs in cells.items():
        label, system, robots, tasks, kbps, loss, security = key
        lines.append(f"{label}: {system} {robots}r {tasks}t {kbps:g}k {loss:g}% {security}")
        lines.append("  rep  completion s  coordination s  query p99 s  wire B/task")
        for r in sorted(runs, key=lambda r: r.rep):
            lines.append(f"  {r.rep:>3}  {r.completion_s:>12.1f}  {r.coordination_s:>14.1f}  "
                         f"{r.query_p99_ms / 1000:>11.2f}  {r.wire_bytes / r.tasks:>11,.0f}")
        s = summary(runs)
        lines.append(f"  {s['runs']} runs: completion median {s['completion_median_s']:.1f} s, slowest "
                     f"{s['slowest_over_median']:.2f}x the median; query p99 at most {s['query_p99_max_s']:.2f} s; "
                     f"wire {s['wire_bytes_per_task']:,.0f} B per task (median)")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.spread", description=__doc__.split("\n\n")[0])
    p.add_argument("csv", type=Path, nargs="+", help="coapkb bench --out CSVs")
    args = p.parse_args(argv)
    rows = [(path.stem, row) for path in args.csv for row in read_rows(path)]
    print("\n".join(report(rows)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
