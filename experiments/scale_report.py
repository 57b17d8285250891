"""The team-size sweep's table and figure: bytes and completion per task against team size.

    .venv/bin/python -m experiments.scale_report [experiments/results/scale.csv]

Reads the rows of ``sudo .venv/bin/python -m experiments.sweep --profile scale`` and writes
``experiments/results/scale.md`` (one line per run: per-task bytes and time,
what the busiest robot's radio and the central server's link carried, the
tasks' fates, why a run failed) and ``experiments/results/figures/scale.png``
(bytes per task and completion per task against team size, one panel per loss
rate, a cross where a run failed).  A point is the median over the repetitions.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from coapkb.bench.row import BenchRow, read_rows

ROOT = Path(__file__).resolve().parent.parent

RESULTS = ROOT / "experiments" / "results"
STYLE = {
    "coap-distributed": ("tab:blue", "-"),
    "coap-central": ("tab:blue", "--"),
    "zmq-distributed": ("tab:orange", "-"),
    "zmq-central": ("tab:orange", "--"),
}


def utilisation(row: BenchRow) -> float | None:
    """The central server's link: the share of its rate its sending used over the run."""
    if row.central_wire_bytes is None or not row.completion_s:
        return None
    return row.central_wire_bytes * 8 / (row.bandwidth_kbps * 1000 * row.completion_s)


def table(rows: Sequence[BenchRow]) -> list[str]:
    lines = [
        "| system | robots | tasks | loss | security | ok | B per task | s per task | busiest robot's B | "
        "central link used | assigned / unavailable / other | why it failed |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(rows, key=lambda r: (r.loss_pct, r.robots, list(STYLE).index(r.system) if r.system in STYLE else 9,
                                         r.rep)):
        fates = r.fates()
        per_task = f"{r.wire_bytes / r.tasks:,.0f}" if r.ok and r.wire_bytes else ""
        time_per_task = f"{r.completion_s / r.tasks:.2f}" if r.ok and r.completion_s else ""
        used = utilisation(r) if r.ok else None
        fate_text = ""
        if fates is not None:
            other = fates.tasks - fates.assigned - fates.unavailable
            fate_text = f"{fates.assigned} / {fates.unavailable} / {other}"
        lines.append(
            f"| {r.system} | {r.robots} | {r.tasks} | {r.loss_pct:g} % | {r.security} | {'yes' if r.ok else 'no'} "
            f"| {per_task} | {time_per_task} | {'' if r.robot_wire_bytes_max is None else f'{r.robot_wire_bytes_max:,}'} "
            f"| {'' if used is None else f'{used:.0%}'} | {fate_text} | {r.error[:120].replace('|', '/')} |"
        )
    return lines


def figure(rows: Sequence[BenchRow], out: Path) -> None:
    losses = sorted({r.loss_pct for r in rows})
    fig, axes = plt.subplots(2, len(losses), figsize=(5.5 * len(losses), 7.5), squeeze=False)
    fig.suptitle("Team size at 35 kbit/s, five tasks per cluster of three (median of the runs; x: a run failed)",
                 fontsize=10)
    for col, loss in enumerate(losses):
        failures: list[tuple[int, str, list[int]]] = []  # (panel row, colour, sizes): drawn last, at the top
        for system, (colour, dash) in STYLE.items():
            by_size: dict[int, list[BenchRow]] = defaultdict(list)
            for r in rows:
                if r.system == system and r.loss_pct == loss:
                    by_size[r.robots].append(r)
            ok = {n: [r for r in rs if r.ok] for n, rs in by_size.items()}
            sizes = sorted(n for n in ok if ok[n])
            for row_no, (metric, scale) in enumerate((("wire_bytes", 1 / 1000), ("completion_s", 1.0))):
                ax = axes[row_no][col]
                ys = [statistics.median(getattr(r, metric) / r.tasks for r in ok[n]) * scale for n in sizes]
                ax.plot(sizes, ys, dash, color=colour, marker="o", label=system)
                failed = sorted(n for n, rs in by_size.items() if any(not r.ok for r in rs))
                if failed:
                    failures.append((row_no, colour, failed))
        for row_no, colour, failed in failures:
            ax = axes[row_no][col]
            top = ax.get_ylim()[1]
            ax.plot(failed, [top] * len(failed), "x", color=colour, markersize=9, clip_on=False)
        axes[0][col].set_title(f"{loss:g} % loss", fontsize=10)
        axes[0][col].set_ylabel("wire kB per task")
        axes[1][col].set_ylabel("completion s per task")
        for row_no in (0, 1):
            ax = axes[row_no][col]
            ax.set_xlabel("robots")
            ax.set_xscale("log")
            ax.set_xticks(sorted({r.robots for r in rows}))
            ax.get_xaxis().set_major_formatter(matplotlib.ticker.ScalarFormatter())
            ax.grid(alpha=0.3)
        axes[0][col].legend(fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.scale_report", description=__doc__.splitlines()[0])
    p.add_argument("csv", nargs="?", type=Path, default=RESULTS / "scale.csv")
    p.add_argument("--out", type=Path, default=RESULTS / "scale.md")
    p.add_argument("--figure", type=Path, default=RESULTS / "figures" / "scale.png")
    args = p.parse_args(argv)
    rows = read_rows(args.csv)
    if not rows:
        print(f"scale_report: no rows in {args.csv}", file=sys.stderr)
        return 1
    figure(rows, args.figure)
    text = [
        "# Team size: the scale sweep",
        "",
        "Generated by `.venv/bin/python -m experiments.scale_report` from `experiments/results/scale.csv`",
        "(`sudo .venv/bin/python -m experiments.sweep --profile scale`). Per-task figures",
        "divide a run's wire bytes and completion time by its tasks; the busiest robot's",
        "bytes are what its own radio sent; the central link used is what the central",
        "server sent over its rate times the run's completion.",
        "",
        f"![bytes and completion per task against team size](figures/{args.figure.name})",
        "",
        *table(rows),
        "",
    ]
    args.out.write_text("\n".join(text), encoding="utf-8")
    print(f"wrote {args.out} and {args.figure}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
