"""The DDS comparison's tables (docs/dds.md) from its benchmark rows.

    .venv/bin/python -m experiments.dds_table experiments/results/dds/*.csv

Per link setting: each system's runs ok / runs and the medians (with their
distribution-free 95 % intervals, experiments/stats.py) of wire bytes,
packets, completion time and query p99; then CoAP ÷ DDS, the median of the
paired ratios (same setting and repetition, hence the same tasks) of wire
bytes, completion and query p99, with its interval.  A pair counts only if
both runs are ok.
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

from coapkb.bench.row import BenchRow
from coapkb.bench.run import SYSTEMS, read_rows
from experiments.stats import median_ci, ratio_ci

ROOT = Path(__file__).resolve().parent.parent

Setting = tuple[int, int, float, float]


def _setting(row: BenchRow) -> Setting:
    return row.robots, row.tasks, row.bandwidth_kbps, row.loss_pct


def _label(s: Setting) -> str:
    return f"{s[0]} robots, {s[1]} tasks, {s[2]:g} kbit/s, {s[3]:g} %"


def medians(rows: list[BenchRow]) -> list[str]:
    groups: dict[Setting, dict[str, list[BenchRow]]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        groups[_setting(row)][row.system].append(row)
    lines = [
        "| setting | system | ok | wire bytes | packets | completion (s) | query p99 (ms) |",
        "|---|---|--:|--:|--:|--:|--:|",
    ]
    for setting, by_system in sorted(groups.items()):
        for system in (s for s in SYSTEMS if s in by_system):
            runs = by_system[system]
            ok = [r for r in runs if r.ok]
            cells = []
            for column, fmt in (("wire_bytes", "{:,.0f}"), ("wire_packets", "{:,.0f}"), ("completion_s", "{:.1f}"),
                                ("query_p99_ms", "{:,.0f}")):
                est = median_ci([getattr(r, column) for r in ok])
                cells.append("" if est is None else est.format(fmt.format))
            lines.append(f"| {_label(setting)} | `{system}` | {len(ok)}/{len(runs)} | " + " | ".join(cells) + " |")
    return lines


def ratios(rows: list[BenchRow], a: str = "coap-distributed", b: str = "dds-distributed") -> list[str]:
    by_key: dict[tuple[Setting, int], dict[str, BenchRow]] = defaultdict(dict)
    for row in rows:
        by_key[(_setting(row), row.rep)][row.system] = row
    settings = sorted({s for s, _ in by_key})
    lines = [
        f"| setting | pairs | `{a}` ÷ `{b}`: wire bytes | completion | query p99 |",
        "|---|--:|--:|--:|--:|",
    ]
    for setting in settings:
        pairs = [(p[a], p[b]) for (s, _), p in sorted(by_key.items()) if s == setting and a in p and b in p
                 and p[a].ok and p[b].ok]
        cells = []
        for column in ("wire_bytes", "completion_s", "query_p99_ms"):
            est = ratio_ci([x.__getattribute__(column) for x, _ in pairs], [y.__getattribute__(column) for _, y in pairs])
            cells.append("" if est is None else est.format(lambda v: f"{v:.3f}" if v < 0.1 else f"{v:.2f}"))
        lines.append(f"| {_label(setting)} | {len(pairs)} | " + " | ".join(cells) + " |")
    return lines


def main() -> None:
    p = argparse.ArgumentParser(prog="python -m experiments.dds_table", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("csv", nargs="*", help="benchmark CSVs (default: experiments/results/dds/*.csv)")
    paths = p.parse_args().csv or sorted(str(p) for p in (ROOT / "experiments" / "results" / "dds").glob("*.csv"))
    rows = [r for path in paths for r in read_rows(path, latest_only=True)]
    print("\n".join(medians(rows)))
    print()
    print("\n".join(ratios(rows)))


if __name__ == "__main__":
    main()
