"""The Zenoh comparison's table (docs/zenoh.md) from its benchmark rows.

    .venv/bin/python -m experiments.zenoh_table [experiments/results/zenoh.csv]

One line per link setting and system: runs ok / runs, and the medians over
the ok repetitions of wire bytes, wire packets, completion time and query
p50/p99, with each system's wire bytes and completion relative to CoAP's
(same mode) in brackets.
"""

from __future__ import annotations

import argparse
import statistics
from collections import defaultdict
from pathlib import Path

from coapkb.bench.row import BenchRow
from coapkb.bench.run import SYSTEMS, read_rows

ROOT = Path(__file__).resolve().parent.parent


def _median(rows: list[BenchRow], column: str) -> float | None:
    values = [getattr(r, column) for r in rows if getattr(r, column) is not None]
    return statistics.median(values) if values else None


def table(rows: list[BenchRow]) -> list[str]:
    groups: dict[tuple[int, int, float, float], dict[str, list[BenchRow]]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        groups[(row.robots, row.tasks, row.bandwidth_kbps, row.loss_pct)][row.system].append(row)
    lines = [
        "| robots, tasks, link | system | ok | wire bytes (÷ CoAP) | packets | completion (÷ CoAP) | query p50 / p99 |",
        "|---|---|---|---|---|---|---|",
    ]
    for (robots, tasks, kbps, loss), by_system in sorted(groups.items()):
        setting = f"{robots}, {tasks}, {kbps:g} kbit/s {loss:g} %"
        for system in (s for s in SYSTEMS if s in by_system):
            runs = by_system[system]
            ok = [r for r in runs if r.ok]
            mode = SYSTEMS[system].mode
            coap = [r for r in by_system.get(f"coap-{mode}", []) if r.ok]
            if not ok:
                lines.append(f"| {setting} | `{system}` | 0/{len(runs)} | failed | | | |")
                continue
            wire, packets, done = (_median(ok, c) for c in ("wire_bytes", "wire_packets", "completion_s"))
            p50, p99 = _median(ok, "query_p50_ms"), _median(ok, "query_p99_ms")
            rel_wire = rel_done = ""
            if coap and not system.startswith("coap-"):
                rel_wire = f" ({wire / _median(coap, 'wire_bytes'):.2f})"
                rel_done = f" ({done / _median(coap, 'completion_s'):.2f})"
            lines.append(
                f"| {setting} | `{system}` | {len(ok)}/{len(runs)} | {wire:,.0f}{rel_wire} | {packets:,.0f} "
                f"| {done:.1f} s{rel_done} | {p50:.0f} / {p99:.0f} ms |"
            )
    return lines


def main() -> None:
    p = argparse.ArgumentParser(prog="python -m experiments.zenoh_table", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("csv", nargs="?", default=str(ROOT / "experiments" / "results" / "zenoh.csv"),
                   help="benchmark CSV (default: experiments/results/zenoh.csv)")
    path = p.parse_args().csv
    print("\n".join(table(read_rows(path, latest_only=True))))


if __name__ == "__main__":
    main()
