#!/usr/bin/env python3
"""``experiments/results/report.md`` from a benchmark CSV: setup, commands,
key ratios next to the seed paper's, tables, figures and notes.

    .venv/bin/python experiments/report.py experiments/results/quick.csv

Every number is computed from the CSV; nothing is typed in by hand except the
seed's own figures (its ~42 % byte saving).  Ratios compare two systems only
on *paired* runs -- the same robots, tasks, bandwidth, loss and repetition
(hence the same task list) -- and are summarised by their geometric mean and
range, so one slow outlier cannot dominate.
"""

from __future__ import annotations

import argparse
import datetime as dt
import math
import os
import platform
import statistics
import sys
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from coapkb.bench.run import SYSTEMS, BenchRow, read_rows

#: The seed's headline (section V, Fig. 6): distributed uses ~42 % fewer bytes
#: than centralised at 35 kbit/s, 5 tasks, 2 % loss, "not much" different at 20 %.
SEED_BYTE_SAVING = 0.42

SETTING = ("robots", "tasks", "bandwidth_kbps", "loss_pct", "rep")
FIGURE_TITLES = {
    "fig06_bytes_vs_loss.png": "Fig. 6 - bytes vs loss, distributed vs central, per team size",
    "fig07_bytes_vs_robots.png": "Fig. 7 - bytes vs team size, distributed, per bandwidth",
    "fig08_bytes_vs_tasks.png": "Fig. 8 - bytes vs tasks, per loss",
    "fig09_bytes_difference.png": "Fig. 9 - central minus distributed bytes vs tasks",
    "fig10_completion_vs_tasks.png": "Fig. 10 - completion time vs tasks, per loss and bandwidth",
    "fig11_completion_difference.png": "Fig. 11 - central minus distributed completion time vs tasks",
    "fig12_completion_per_robots.png": "Fig. 12 - completion time vs tasks per team size, distributed",
    "transport_bytes.png": "Transport comparison - bytes per system and link",
    "transport_time.png": "Transport comparison - completion time per system and link",
    "query_latency.png": "Remote query latency p50/p99 per system",
}


@dataclass(frozen=True)
class Ratio:
    """A/B over paired runs: geometric mean, range, and how many pairs."""

    gmean: float
    low: float
    high: float
    n: int

    def as_factor(self) -> str:
        return f"x{self.gmean:.2f} ({self.low:.2f}-{self.high:.2f}, n={self.n})"

    def as_saving(self) -> str:
        """1 - A/B as a percentage: positive = A uses less."""
        return (f"{100 * (1 - self.gmean):.0f} % ({100 * (1 - self.high):.0f} to {100 * (1 - self.low):.0f}, "
                f"n={self.n})")


def _setting(row: BenchRow) -> tuple[Any, ...]:
    return tuple(getattr(row, c) for c in SETTING)


def paired(rows: Sequence[BenchRow], a: str, b: str,
           where: Any = None) -> list[tuple[BenchRow, BenchRow]]:
    """(row of a, row of b) for every setting where both have an ok row (and ``where(row)`` holds)."""
    by: dict[str, dict[tuple[Any, ...], BenchRow]] = defaultdict(dict)
    for r in rows:
        if r.ok and (where is None or where(r)):
            by[r.system][_setting(r)] = r
    return [(by[a][k], by[b][k]) for k in sorted(by[a].keys() & by[b].keys())]


def ratio(pairs: Iterable[tuple[BenchRow, BenchRow]], column: str) -> Ratio | None:
    values = [getattr(x, column) / getattr(y, column) for x, y in pairs if getattr(x, column) and getattr(y, column)]
    if not values:
        return None
    return Ratio(math.exp(statistics.fmean(math.log(v) for v in values)), min(values), max(values), len(values))


def _fmt(r: Ratio | None, saving: bool = False) -> str:
    if r is None:
        return "no paired runs"
    return r.as_saving() if saving else r.as_factor()


def _kb(v: Any) -> str:
    return "-" if v is None else f"{v / 1000:.1f}"


def _s(v: Any) -> str:
    return "-" if v is None else f"{v:.1f}"


def _md_table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return lines


def _systems(rows: Sequence[BenchRow]) -> list[str]:
    present = {r.system for r in rows}
    return [s for s in SYSTEMS if s in present]


def _values(rows: Sequence[BenchRow], column: str) -> list[Any]:
    return sorted({getattr(r, column) for r in rows if getattr(r, column) is not None})


def _g(v: float) -> str:
    return f"{v:g}"


# --------------------------------------------------------------------------- sections


def section_setup(rows: Sequence[BenchRow], csv_path: Path, profile: str) -> list[str]:
    ok = [r for r in rows if r.ok]
    starts = sorted(r.started_at for r in rows if r.started_at)
    wall = sum(r.wall_s or 0 for r in rows)
    span = ""
    if starts:
        first = dt.datetime.fromisoformat(starts[0])
        last_row = max((r for r in rows if r.started_at), key=lambda r: r.started_at)
        end = dt.datetime.fromisoformat(last_row.started_at) + dt.timedelta(seconds=last_row.wall_s or 0)
        span = f"; first run started {starts[0]}, last ended {(end - first).total_seconds() / 60:.1f} min later"
    lines = [
        "## Setup",
        "",
        f"- **Data**: `{_rel(csv_path)}`, {len(rows)} runs, {len(ok)} ok, {len(rows) - len(ok)} failed; "
        f"sum of run wall times {wall / 60:.1f} min{span}.",
        f"- **Matrix covered** (profile `{profile}`): robots {', '.join(map(str, _values(rows, 'robots')))}; "
        f"tasks {', '.join(map(str, _values(rows, 'tasks')))}; "
        f"bandwidth {', '.join(_g(v) for v in _values(rows, 'bandwidth_kbps'))} kbit/s; "
        f"loss {', '.join(_g(v) for v in _values(rows, 'loss_pct'))} %; "
        f"repetitions {len(_values(rows, 'rep'))}; CoAP retransmission "
        f"{', '.join(v for v in _values(rows, 'retransmission_profile') if v != 'tcp') or '-'}.",
        f"- **Machine**: {os.cpu_count()} CPUs, Linux {platform.release()}, Python {platform.python_version()}. "
        "Every robot, the central KB server and the task feeder are separate OS processes, each in its own "
        "network namespace (`coapkb.bench.linkemu.Testbed`): a `tbf` shaper at the given rate on both directions of "
        "each robot's and the server's link, independent per-packet loss charged to the sender, no added delay "
        "(the kernel has no netem). The feeder's link is unshaped and lossless (it is the seed's external task "
        "source).",
        "- **Bytes** (`wire_bytes`) are what every host's interface put on its link during the run: Ethernet "
        "frames with IP/UDP/TCP headers, TCP handshakes and ACKs, all retransmissions, and the packets the loss "
        "rule then dropped -- what the seed measured with Wireshark. **Completion time** is from feeding the "
        "first task until every robot finished executing its share (execution is simulated 50x faster than real "
        "time, so it is mostly coordination).",
        "",
        "Systems:",
        "",
    ]
    lines += _md_table(("system", "what"), ((f"`{s}`", SYSTEMS[s].description) for s in _systems(rows)))
    return lines


def section_commands(csv_path: Path, profile: str) -> list[str]:
    rel = _rel(csv_path)
    return [
        "## Commands",
        "",
        "```sh",
        "make venv                                                   # once",
        f"sudo .venv/bin/python experiments/sweep.py --profile {profile}      # resumable; --jobs N runs N at once",
        f".venv/bin/python experiments/figures.py {rel}",
        f".venv/bin/python experiments/report.py {rel}",
        "# one run by hand:",
        "sudo .venv/bin/coapkb bench --robots 3 --tasks 5 --bandwidth 35 --loss 2 \\",
        "    --systems coap-distributed,coap-central,zmq-distributed,zmq-central --out /tmp/bench.csv",
        "```",
        "",
        "Details and definitions: [`docs/benchmarks.md`](../../docs/benchmarks.md).",
    ]


def key_ratios(rows: Sequence[BenchRow]) -> list[tuple[str, str, str, str]]:
    """(comparison, bytes, completion time, the seed's number) rows."""
    out: list[tuple[str, str, str, str]] = []
    for label, dist, cent in (
        ("seed stack (ZeroMQ, SPARQL + JSON)", "seed-distributed", "seed-central"),
        ("CoAP + compact", "coap-distributed", "coap-central"),
        ("ZeroMQ + compact", "zmq-distributed", "zmq-central"),
    ):
        pairs = paired(rows, dist, cent)
        if pairs:
            out.append((f"distributed vs central, {label}: saving", _fmt(ratio(pairs, "wire_bytes"), True),
                        _fmt(ratio(pairs, "completion_s"), True), f"~{SEED_BYTE_SAVING:.0%} fewer bytes; faster"))
    for label, a, b, seed in (
        ("CoAP vs ZeroMQ, distributed (both compact)", "coap-distributed", "zmq-distributed", "-"),
        ("CoAP vs ZeroMQ, central (both compact)", "coap-central", "zmq-central", "-"),
        ("compact vs seed wire (ZeroMQ, distributed)", "zmq-distributed", "seed-distributed", "-"),
        ("compact vs seed wire (ZeroMQ, central)", "zmq-central", "seed-central", "-"),
        ("coapkb (CoAP, compact, distributed) vs the seed's system", "coap-distributed", "seed-distributed", "-"),
    ):
        pairs = paired(rows, a, b)
        if pairs:
            out.append((f"{label}: A/B", _fmt(ratio(pairs, "wire_bytes")), _fmt(ratio(pairs, "completion_s")), seed))
    return out


def section_ratios(rows: Sequence[BenchRow]) -> list[str]:
    lines = [
        "## Key ratios",
        "",
        "Paired runs only (same robots, tasks, bandwidth, loss and repetition, hence the same tasks). "
        "\"saving\" = 1 - A/B (positive: the first system uses less); \"A/B\" = geometric mean of the "
        "per-pair ratios, with their range and the number of pairs.",
        "",
    ]
    table = key_ratios(rows)
    if not table:
        return lines + ["No paired runs: the CSV has fewer than two systems per setting."]
    lines += _md_table(("comparison", "bytes on the wire", "completion time", "seed paper"), table)

    # The seed's headline condition, per stack and team size.
    bws, tasks, losses = _values(rows, "bandwidth_kbps"), _values(rows, "tasks"), _values(rows, "loss_pct")
    bw = 35.0 if 35.0 in bws else (bws[0] if bws else None)
    t = 5 if 5 in tasks else (tasks[0] if tasks else None)
    if bw is not None and t is not None:
        head = []
        for dist, cent in (("seed-distributed", "seed-central"), ("coap-distributed", "coap-central"),
                           ("zmq-distributed", "zmq-central")):
            for loss in losses:
                for robots in _values(rows, "robots"):
                    want = (bw, t, loss, robots)
                    pairs = paired(rows, dist, cent, lambda r, want=want: (  # type: ignore[misc]
                        r.bandwidth_kbps, r.tasks, r.loss_pct, r.robots) == want)
                    r = ratio(pairs, "wire_bytes")
                    if r is not None:
                        head.append((dist.split("-")[0], robots, _g(loss), f"{100 * (1 - r.gmean):.0f} %", r.n))
        if head:
            lines += ["", f"Distributed vs central byte saving in the seed's Fig. 6 setting ({_g(bw)} kbit/s, {t} tasks); "
                      f"the seed reports ~{SEED_BYTE_SAVING:.0%} at 2 % loss and about the same at 20 %:", ""]
            lines += _md_table(("stack", "robots", "loss %", "saving", "pairs"), head)

    # CoAP vs ZeroMQ by loss: where the time ratio flips.
    by_loss = []
    for loss in losses:
        for a, b in (("coap-distributed", "zmq-distributed"), ("coap-central", "zmq-central")):
            pairs = paired(rows, a, b, lambda r, loss=loss: r.loss_pct == loss)  # type: ignore[misc]
            rb, rt = ratio(pairs, "wire_bytes"), ratio(pairs, "completion_s")
            if rb and rt:
                by_loss.append((_g(loss), f"{a} / {b}", f"x{rb.gmean:.2f}", f"x{rt.gmean:.2f}", rb.n))
    if by_loss:
        lines += ["", "CoAP vs ZeroMQ by loss level (A/B, geometric mean over the paired settings):", ""]
        lines += _md_table(("loss %", "A / B", "bytes", "completion time", "pairs"), by_loss)
    return lines


def section_tables(rows: Sequence[BenchRow]) -> list[str]:
    systems = _systems(rows)
    cells: dict[tuple[Any, ...], dict[str, list[BenchRow]]] = defaultdict(lambda: defaultdict(list))
    for r in rows:
        cells[(r.robots, r.tasks, r.bandwidth_kbps, r.loss_pct)][r.system].append(r)

    def cell(rs: list[BenchRow], column: str, fmt: Any) -> str:
        good = [getattr(r, column) for r in rs if r.ok and getattr(r, column) is not None]
        bad = sum(1 for r in rs if not r.ok)
        text = fmt(statistics.fmean(good)) if good else "-"
        return text + (f" ({bad} failed)" if bad else "")

    lines = ["## Results", "", "Means over repetitions of the ok runs; \"failed\" runs are listed below.", ""]
    for title, column, fmt in (
        ("Bytes on the wire (kB)", "wire_bytes", _kb),
        ("Task completion time (s)", "completion_s", _s),
        ("Retransmissions (CoAP: retransmitted CONs; ZeroMQ: TCP RetransSegs)", "retransmissions", lambda v: f"{v:.0f}"),
        ("Remote query latency p99 (ms)", "query_p99_ms", lambda v: f"{v:.0f}"),
    ):
        lines += [f"### {title}", ""]
        lines += _md_table(
            ("robots", "tasks", "kbit/s", "loss %", *systems),
            ((k[0], k[1], _g(k[2]), _g(k[3]), *(cell(cells[k][s], column, fmt) for s in systems))
             for k in sorted(cells)),
        )
        lines.append("")
    return lines


def section_figures(figdir: Path, report_dir: Path) -> list[str]:
    present = [name for name in FIGURE_TITLES if (figdir / name).exists()]
    if not present:
        return ["## Figures", "", "No figures yet: run `experiments/figures.py` first."]
    lines = ["## Figures", ""]
    for name in present:
        rel = os.path.relpath(figdir / name, report_dir)
        lines += [f"### {FIGURE_TITLES[name]}", "", f"![{FIGURE_TITLES[name]}]({rel})", ""]
    return lines


def section_notes(rows: Sequence[BenchRow]) -> list[str]:
    """Where distribution and CoAP win or lose, stated from the data."""
    lines = [
        "## Where each choice wins or loses (from this data)",
        "",
        "Why (packet traces, kernel counters, the failure modes): "
        "[`docs/benchmarks.md`, \"What we found, and why\"](../../docs/benchmarks.md#what-we-found-and-why).",
        "",
    ]
    for label, a, b in (
        ("Distribution (CoAP)", "coap-distributed", "coap-central"),
        ("Distribution (ZeroMQ)", "zmq-distributed", "zmq-central"),
        ("Distribution (seed stack)", "seed-distributed", "seed-central"),
        ("CoAP over ZeroMQ (distributed)", "coap-distributed", "zmq-distributed"),
        ("CoAP over ZeroMQ (central)", "coap-central", "zmq-central"),
        ("Compact wire over the seed's (ZeroMQ, distributed)", "zmq-distributed", "seed-distributed"),
    ):
        pairs = paired(rows, a, b)
        if not pairs:
            continue
        fewer = sum(1 for x, y in pairs if x.wire_bytes < y.wire_bytes)
        faster = sum(1 for x, y in pairs if x.completion_s < y.completion_s)
        slower = [(x, y) for x, y in pairs if x.completion_s >= y.completion_s]
        worst = max(slower, key=lambda p: p[0].completion_s / p[1].completion_s, default=None)
        text = (f"- **{label}**: fewer bytes in {fewer} of {len(pairs)} paired settings, "
                f"faster in {faster} of {len(pairs)}.")
        if worst is not None:
            x, y = worst
            text += (f" Largest slow-down x{x.completion_s / y.completion_s:.1f} at {x.robots} robots, "
                     f"{x.tasks} tasks, {_g(x.bandwidth_kbps)} kbit/s, {_g(x.loss_pct)} % loss "
                     f"({x.completion_s:.1f} s vs {y.completion_s:.1f} s).")
        lines.append(text)
    tcp = [r for r in rows if r.transport == "zmq" and r.tcp_aborts is not None]
    if tcp:
        aborted = [r for r in tcp if r.tcp_aborts > 0]
        lines.append(
            f"- **ZeroMQ connections given up by the kernel** (`tcp_aborts` > 0): {len(aborted)} of {len(tcp)} "
            f"ZeroMQ runs; {sum(1 for r in aborted if not r.ok)} of those failed, against "
            f"{sum(1 for r in tcp if not r.tcp_aborts and not r.ok)} failures among the others."
        )
    failed = [r for r in rows if not r.ok]
    lines += ["", "### Failed runs", ""]
    if not failed:
        lines.append("None.")
    else:
        lines += _md_table(
            ("system", "robots", "tasks", "kbit/s", "loss %", "rep", "TCP aborts", "error"),
            ((r.system, r.robots, r.tasks, _g(r.bandwidth_kbps), _g(r.loss_pct), r.rep,
              "-" if r.tcp_aborts is None else r.tcp_aborts,
              (r.error or "").replace("|", "/")[:200]) for r in failed),
        )
    lines += [
        "",
        "### Caveats",
        "",
        "- No propagation delay (the kernel lacks netem): round trips are serialisation plus queueing plus "
        "processing. A real radio adds tens of ms per hop, which would lengthen every exchange for both "
        "transports and make TCP's handshakes cost more.",
        "- The shaper lets an idle link send ~2 KiB at once (tbf burst), so small exchanges on an idle "
        "35 kbit/s link are faster than their serialisation time; the long-run rate is exact.",
        "- Loss is independent per packet (no bursts); each host has its own link (no shared channel).",
        "- `app_bytes` lacks the central server's replies (it keeps no counters); compare systems on `wire_bytes`.",
        "- Completion times on a 2-core machine include the robots' CPU time; byte counts do not depend on it.",
        "- One repetition per setting in the quick profile: loss is random, so single-run times at high loss "
        "vary by tens of percent (a few unlucky retransmission back-offs dominate). Bytes vary much less.",
    ]
    return lines


def _rel(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def build_report(rows: Sequence[BenchRow], csv_path: Path, figdir: Path, report_path: Path,
                 profile: str | None = None) -> str:
    """The whole markdown text."""
    profile = profile or csv_path.stem
    lines = [
        f"# Benchmark report: `{profile}` profile",
        "",
        "Reproduction of the seed paper's experiment (section IV-V: distributed vs centralised knowledge base, "
        "bytes exchanged and task completion time on slow lossy links) with coapkb's CoAP/UDP stack, the same "
        "agent over ZeroMQ/TCP, and the seed's own wire format. Generated by `experiments/report.py`.",
        "",
    ]
    for section in (
        section_setup(rows, csv_path, profile),
        section_commands(csv_path, profile),
        section_ratios(rows),
        section_notes(rows),
        section_tables(rows),
        section_figures(figdir, report_path.parent),
    ):
        lines += section + [""]
    return "\n".join(lines).rstrip() + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Markdown report from a coapkb benchmark CSV.")
    p.add_argument("csv", type=Path, nargs="?", default=ROOT / "experiments" / "results" / "quick.csv")
    p.add_argument("--out", type=Path, help="default: report.md next to the CSV")
    p.add_argument("--figures", type=Path, help="figure directory (default: figures/ next to the CSV)")
    p.add_argument("--profile", help="profile name for the title (default: the CSV's name)")
    args = p.parse_args(argv)
    rows = read_rows(args.csv)
    if not rows:
        print(f"report: no rows in {args.csv}", file=sys.stderr)
        return 1
    out = args.out or args.csv.parent / "report.md"
    figdir = args.figures or args.csv.parent / "figures"
    out.write_text(build_report(rows, args.csv, figdir, out, args.profile), encoding="utf-8")
    print(f"report written to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
