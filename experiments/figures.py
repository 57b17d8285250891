"""Figures from a benchmark CSV: the seed paper's Figs. 6-12 and the transport comparison.

    .venv/bin/python -m experiments.figures experiments/results/quick.csv

Writes PNGs into ``experiments/results/figures/`` (``--outdir`` to change).
Each figure is drawn from whatever subset of the matrix the CSV holds; a
figure whose data is missing is skipped with a one-line note, never an error.
Only rows with ``ok=True`` are plotted (a failed run's bytes and times are
those of a partial run).  A point is the median over the repetitions; Figs.
6-12 draw its distribution-free interval as an error bar (Figs. 9 and 11: the
median of the paired per-repetition differences), all from
``experiments/stats.py`` like the report's tables.  One repetition draws no bar.

The seed compares *one* stack, distributed against centralised.  We have
three stacks ("families"): CoAP with compact answers, ZeroMQ with compact
answers and the seed's own ZeroMQ + SPARQL text + SPARQL-JSON.  The seed's
figures are therefore drawn once per family that has the data, as panels.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from coapkb.bench.run import SYSTEMS, BenchRow
from experiments.common import benchmark_rows
from experiments.stats import Estimate, median_ci

ROOT = Path(__file__).resolve().parent.parent

FAMILIES: dict[str, tuple[str, str]] = {
    # family: (distributed system, central system)
    "CoAP + compact CBOR": ("coap-distributed", "coap-central"),
    "ZeroMQ + compact CBOR": ("zmq-distributed", "zmq-central"),
    "seed: ZeroMQ + SPARQL/JSON": ("seed-distributed", "seed-central"),
}
SYSTEM_ORDER = list(SYSTEMS)
COLOURS = {
    "coap-distributed": "#1f77b4", "coap-central": "#aec7e8",
    "zmq-distributed": "#d62728", "zmq-central": "#ff9896",
    "seed-distributed": "#2ca02c", "seed-central": "#98df8a",
}
ROBOT_COLOURS = {3: "#1f77b4", 6: "#ff7f0e", 9: "#2ca02c"}
#: One colour per transport (tab10, colour-blind-safe order), whatever the
#: mode; a central system is the same colour, lighter and hatched.
PALETTE = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22",
           "#17becf")
TRANSPORTS = list(dict.fromkeys(s.rsplit("-", 1)[0] for s in SYSTEMS))
TRANSPORT_COLOURS = {t: PALETTE[i % len(PALETTE)] for i, t in enumerate(TRANSPORTS)}


def transport_of(system: str) -> str:
    return system.rsplit("-", 1)[0]


def _no_data(ax: Any, text: str = "no data for this panel") -> None:
    ax.text(0.5, 0.5, text, transform=ax.transAxes, ha="center", va="center", color="grey", fontsize=9)


@dataclass(frozen=True)
class Point:
    """One system at one setting: medians over the repetitions (``wire`` and
    ``completion`` with their intervals)."""

    system: str
    robots: int
    tasks: int
    bandwidth: float
    loss: float
    wire_bytes: float
    completion_s: float
    p50_ms: float | None
    p99_ms: float | None
    n: int
    wire: Estimate
    completion: Estimate


class Data:
    """The ok rows of a CSV, per (system, robots, tasks, bandwidth, loss): medians over repetitions."""

    def __init__(self, rows: Sequence[BenchRow]) -> None:
        groups: dict[tuple[Any, ...], list[BenchRow]] = defaultdict(list)
        self.failed = [r for r in rows if not r.ok]
        for r in rows:
            if r.ok and r.system in SYSTEMS:
                groups[(r.system, r.robots, r.tasks, r.bandwidth_kbps, r.loss_pct)].append(r)
        self.points: dict[tuple[Any, ...], Point] = {}
        for key, rs in groups.items():
            wire, completion = median_ci(r.wire_bytes for r in rs), median_ci(r.completion_s for r in rs)
            if wire is None or completion is None:  # an ok row always has both; skip a malformed one
                continue
            p50, p99 = median_ci(r.query_p50_ms for r in rs), median_ci(r.query_p99_ms for r in rs)
            self.points[key] = Point(
                *key, wire_bytes=wire.value, completion_s=completion.value,
                p50_ms=p50.value if p50 else None, p99_ms=p99.value if p99 else None,
                n=len(rs), wire=wire, completion=completion,
            )
        self.rows = [r for r in rows if r.ok]
        self._groups = groups

    def difference(self, minuend: str, subtrahend: str, robots: int, tasks: int, bandwidth: float, loss: float,
                   attr: str) -> Estimate | None:
        """The median of ``minuend - subtrahend`` over the repetitions both ran
        at this setting (paired by rep: the same task list), with its interval."""
        def by_rep(system: str) -> dict[int, float]:
            rs = self._groups.get((system, robots, tasks, float(bandwidth), float(loss)), [])
            return {r.rep: getattr(r, attr) for r in rs if getattr(r, attr) is not None}
        m, s = by_rep(minuend), by_rep(subtrahend)
        return median_ci(m[rep] - s[rep] for rep in sorted(m.keys() & s.keys()))

    def get(self, system: str, robots: int, tasks: int, bandwidth: float, loss: float) -> Point | None:
        return self.points.get((system, robots, tasks, float(bandwidth), float(loss)))

    def values(self, attr: str) -> list[Any]:
        return sorted({getattr(p, attr) for p in self.points.values()})

    def systems(self) -> list[str]:
        present = {p.system for p in self.points.values()}
        return [s for s in SYSTEM_ORDER if s in present]

    def families(self, need_central: bool = True) -> list[tuple[str, str, str]]:
        present = set(self.systems())
        return [(name, d, c) for name, (d, c) in FAMILIES.items() if d in present and (c in present or not need_central)]


def _pick(values: Sequence[float], preferred: float) -> float | None:
    """``preferred`` if present, else the closest value present."""
    if not values:
        return None
    return preferred if preferred in values else min(values, key=lambda v: abs(v - preferred))


def _panels(n: int, title: str, width: float = 5.0) -> tuple[Any, list[Any]]:
    fig, axes = plt.subplots(1, n, figsize=(width * n, 4.0), squeeze=False)
    fig.suptitle(title, fontsize=11)
    return fig, list(axes[0])


def _save(fig: Any, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _legend(ax: Any, size: int) -> None:
    """A legend if the panel has labelled lines (a family may lack a setting)."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=size)


def _kb(v: float) -> float:
    return v / 1000.0


def _line(ax: Any, xs: list[float], ys: Sequence[Estimate | None], scale: Callable[[float], float] = float,
          **kw: Any) -> bool:
    """Medians joined by a line, each with its interval as an error bar (none for one run)."""
    pts = [(x, y.map(scale)) for x, y in zip(xs, ys) if y is not None]
    if not pts:
        return False
    # Centralised systems are dashed; give them square markers so the legend tells them apart.
    kw.setdefault("marker", "s" if kw.get("linestyle") == "--" else "o")
    low, high = zip(*(p[1].yerr() for p in pts))
    ax.errorbar([p[0] for p in pts], [p[1].value for p in pts], yerr=[low, high], capsize=3, elinewidth=0.8, **kw)
    return True


# --------------------------------------------------------------------------- the seed's figures


def fig6(data: Data, out: Path) -> Path | str:
    """Bytes vs loss at 35 kbit/s and 5 tasks, per team size, distributed vs central."""
    fams = data.families()
    bw = _pick(data.values("bandwidth"), 35)
    tasks = _pick(data.values("tasks"), 5)
    if not fams or bw is None or tasks is None:
        return "no distributed/central pair"
    fig, axes = _panels(len(fams), f"Fig. 6: bytes on the wire vs loss ({bw:g} kbit/s, {tasks} tasks)")
    drawn = False
    for ax, (name, dist, cent) in zip(axes, fams):
        for robots in data.values("robots"):
            losses = [x for x in data.values("loss") if data.get(dist, robots, tasks, bw, x) or data.get(cent, robots, tasks, bw, x)]
            for system, style in ((dist, "-"), (cent, "--")):
                ys = [(p.wire if (p := data.get(system, robots, tasks, bw, x)) else None) for x in losses]
                drawn |= _line(ax, losses, ys, _kb, linestyle=style, color=ROBOT_COLOURS.get(robots),
                               label=f"{robots} robots, {SYSTEMS[system].mode}")
        ax.set(title=name, xlabel="loss (%)", ylabel="kB on the wire", xticks=data.values("loss"))
        if not ax.lines and not ax.collections:
            _no_data(ax)
        _legend(ax, 7)
        ax.set_ylim(bottom=0)
        ax.margins(x=0.08)  # points at the first and last loss stay off the frame
    return _save(fig, out / "fig06_bytes_vs_loss.png") if drawn else "no points at that bandwidth/tasks"


def fig7(data: Data, out: Path) -> Path | str:
    """Bytes vs team size, distributed, one line per bandwidth (5 tasks, lowest loss)."""
    fams = data.families(need_central=False)
    tasks = _pick(data.values("tasks"), 5)
    loss = _pick(data.values("loss"), 2)
    if len(data.values("robots")) < 2 or not fams or tasks is None:
        return "needs at least two team sizes"
    fig, axes = _panels(len(fams), f"Fig. 7: bytes vs robots, distributed ({tasks} tasks, {loss:g} % loss)")
    drawn = False
    for ax, (name, dist, _) in zip(axes, fams):
        for bw in data.values("bandwidth"):
            robots = [r for r in data.values("robots") if data.get(dist, r, tasks, bw, loss)]
            if len(robots) < 2:
                continue
            ys = [data.get(dist, r, tasks, bw, loss).wire for r in robots]  # type: ignore[union-attr]
            drawn |= _line(ax, robots, ys, _kb, label=f"{bw:g} kbit/s")
        ax.set(title=name, xlabel="robots", ylabel="kB on the wire", xticks=data.values("robots"))
        _legend(ax, 7)
        ax.set_ylim(bottom=0)
    return _save(fig, out / "fig07_bytes_vs_robots.png") if drawn else "no bandwidth with two team sizes"


def fig8(data: Data, out: Path) -> Path | str:
    """Bytes vs tasks per loss, 3 robots, 35 kbit/s, distributed vs central."""
    fams = data.families()
    bw = _pick(data.values("bandwidth"), 35)
    if len(data.values("tasks")) < 2 or not fams or bw is None:
        return "needs at least two task counts"
    fig, axes = _panels(len(fams), f"Fig. 8: bytes vs tasks (3 robots, {bw:g} kbit/s)")
    drawn = False
    for ax, (name, dist, cent) in zip(axes, fams):
        for loss in data.values("loss"):
            for system, style in ((dist, "-"), (cent, "--")):
                tasks = [t for t in data.values("tasks") if data.get(system, 3, t, bw, loss)]
                if len(tasks) < 2:
                    continue
                ys = [data.get(system, 3, t, bw, loss).wire for t in tasks]  # type: ignore[union-attr]
                drawn |= _line(ax, tasks, ys, _kb, linestyle=style, label=f"{loss:g} % loss, {SYSTEMS[system].mode}")
        ax.set(title=name, xlabel="tasks", ylabel="kB on the wire", xticks=data.values("tasks"))
        _legend(ax, 7)
        ax.set_ylim(bottom=0)
    return _save(fig, out / "fig08_bytes_vs_tasks.png") if drawn else "no loss level with two task counts"


def _difference_figure(data: Data, out: Path, attr: str, scale: Callable[[float], float], ylabel: str,
                       title: str, filename: str) -> Path | str:
    fams = data.families()
    bw = _pick(data.values("bandwidth"), 35)
    loss = _pick(data.values("loss"), 2)
    if len(data.values("tasks")) < 2 or not fams or bw is None or loss is None:
        return "needs at least two task counts and a distributed/central pair"
    fig, axes = _panels(len(fams), f"{title} ({bw:g} kbit/s, {loss:g} % loss)")
    drawn = False
    for ax, (name, dist, cent) in zip(axes, fams):
        for robots in data.values("robots"):
            xs: list[float] = []
            ys: list[Estimate | None] = []
            for t in data.values("tasks"):
                diff = data.difference(cent, dist, robots, t, bw, loss, attr)
                if diff is not None:
                    xs.append(t)
                    ys.append(diff)
            if len(xs) >= 2:
                drawn |= _line(ax, xs, ys, scale, color=ROBOT_COLOURS.get(robots), label=f"{robots} robots")
        if not ax.get_legend_handles_labels()[0]:
            _no_data(ax, "no data: this family ran no two task counts\nin both modes at this setting")
        ax.axhline(0, color="grey", linewidth=0.8)
        ax.set(title=name, xlabel="tasks", ylabel=ylabel, xticks=data.values("tasks"))
        _legend(ax, 7)
    return _save(fig, out / filename) if drawn else "no team size with two task counts in both modes"


def fig9(data: Data, out: Path) -> Path | str:
    """Central minus distributed bytes vs tasks."""
    return _difference_figure(data, out, "wire_bytes", _kb, "central - distributed (kB)",
                              "Fig. 9: extra bytes of the centralised system", "fig09_bytes_difference.png")


def fig10(data: Data, out: Path) -> Path | str:
    """Completion time vs tasks per loss, 3 robots, one panel per bandwidth, distributed vs central.
    One figure row per family."""
    fams = data.families()
    bws = data.values("bandwidth")
    if len(data.values("tasks")) < 2 or not fams or not bws:
        return "needs at least two task counts"
    fig, grid = plt.subplots(len(fams), len(bws), figsize=(4.5 * len(bws), 3.6 * len(fams)), squeeze=False)
    fig.suptitle("Fig. 10: task completion time vs tasks (3 robots)", fontsize=11)
    drawn = False
    for row, (name, dist, cent) in zip(grid, fams):
        for ax, bw in zip(row, bws):
            for loss in data.values("loss"):
                for system, style in ((dist, "-"), (cent, "--")):
                    tasks = [t for t in data.values("tasks") if data.get(system, 3, t, bw, loss)]
                    if len(tasks) < 2:
                        continue
                    ys = [data.get(system, 3, t, bw, loss).completion for t in tasks]  # type: ignore[union-attr]
                    drawn |= _line(ax, tasks, ys, linestyle=style, label=f"{loss:g} %, {SYSTEMS[system].mode}")
            ax.set(title=f"{name}, {bw:g} kbit/s", xlabel="tasks", ylabel="completion (s)",
                   xticks=data.values("tasks"))
            ax.title.set_fontsize(9)
            _legend(ax, 6)
            ax.set_ylim(bottom=0)
    return _save(fig, out / "fig10_completion_vs_tasks.png") if drawn else "no setting with two task counts"


def fig11(data: Data, out: Path) -> Path | str:
    """Central minus distributed completion time vs tasks."""
    return _difference_figure(data, out, "completion_s", float, "central - distributed (s)",
                              "Fig. 11: extra completion time of the centralised system", "fig11_completion_difference.png")


def fig12(data: Data, out: Path) -> Path | str:
    """Completion time vs tasks per team size (distributed), one panel per bandwidth."""
    fams = data.families(need_central=False)
    bws = data.values("bandwidth")
    if len(data.values("tasks")) < 2 or not fams or not bws:
        return "needs at least two task counts"
    fig, grid = plt.subplots(len(fams), len(bws), figsize=(4.5 * len(bws), 3.6 * len(fams)), squeeze=False)
    fig.suptitle("Fig. 12: completion time vs tasks per team size, distributed", fontsize=11)
    drawn = False
    for row, (name, dist, _) in zip(grid, fams):
        for ax, bw in zip(row, bws):
            for robots in data.values("robots"):
                for loss, style in zip(data.values("loss"), ("-", "--", ":", "-.", (0, (1, 3)))):
                    tasks = [t for t in data.values("tasks") if data.get(dist, robots, t, bw, loss)]
                    if len(tasks) < 2:
                        continue
                    ys = [data.get(dist, robots, t, bw, loss).completion for t in tasks]  # type: ignore[union-attr]
                    drawn |= _line(ax, tasks, ys, linestyle=style, color=ROBOT_COLOURS.get(robots),
                                   label=f"{robots} robots, {loss:g} %")
            ax.set(title=f"{name}, {bw:g} kbit/s", xlabel="tasks", ylabel="completion (s)",
                   xticks=data.values("tasks"))
            ax.title.set_fontsize(9)
            _legend(ax, 6)
            ax.set_ylim(bottom=0)
    return _save(fig, out / "fig12_completion_per_robots.png") if drawn else "no team size with two task counts"


# --------------------------------------------------------------------------- beyond the seed


def common_team(data: Data) -> tuple[int, int] | None:
    """The (robots, tasks) pair with the most (system, bandwidth, loss) points."""
    count: dict[tuple[int, int], int] = defaultdict(int)
    for p in data.points.values():
        count[(p.robots, p.tasks)] += 1
    return max(count, key=lambda k: (count[k], -k[0], -k[1])) if count else None


def _setting_bars(data: Data, out: Path, attr: str, estimate: str, scale: Callable[[float], float], ylabel: str,
                  title: str, filename: str) -> Path | str:
    """One bar per system at each setting: the transport's colour, central
    lighter and hatched, the median's interval as an error bar, and a mark
    where a system has no ok run at a setting."""
    team = common_team(data)
    if team is None:
        return "no data"
    robots, tasks = team
    settings = sorted({(p.bandwidth, p.loss) for p in data.points.values() if (p.robots, p.tasks) == team})
    systems = data.systems()
    if len(systems) < 2:
        return "needs at least two systems"
    fig, ax = plt.subplots(figsize=(max(7.0, 1.5 * len(settings) * len(systems) / 3), 4.6))
    width = 0.8 / len(systems)
    missing = []
    for i, system in enumerate(systems):
        xs, ys, low, high = [], [], [], []
        for j, (bw, loss) in enumerate(settings):
            x = j + (i - (len(systems) - 1) / 2) * width
            p = data.get(system, robots, tasks, bw, loss)
            if p is None:
                missing.append(x)
                continue
            value = getattr(p, estimate).map(scale)
            below, above = value.yerr()
            xs.append(x)
            ys.append(scale(getattr(p, attr)))
            low.append(below)
            high.append(above)
        central = SYSTEMS[system].mode == "central"
        ax.bar(xs, ys, width=width, label=system, color=TRANSPORT_COLOURS[transport_of(system)],
               alpha=0.55 if central else 1.0, hatch="//" if central else None, edgecolor="black", linewidth=0.4,
               yerr=[low, high], capsize=2, error_kw={"elinewidth": 0.7})
    for x in missing:  # a system with no ok run there: said, not left as a gap
        ax.text(x, 0, "×", ha="center", va="bottom", color="grey", fontsize=8)
    ax.set_xticks(range(len(settings)), [f"{bw:g} kbit/s\n{loss:g} % loss" for bw, loss in settings], fontsize=8)
    note = "; × = no ok run" if missing else ""
    ax.set(ylabel=ylabel, title=f"{title} ({robots} robots, {tasks} tasks; medians, 95 % intervals{note})")
    ax.legend(fontsize=8, ncol=2, loc="upper left", bbox_to_anchor=(1.01, 1.0), title="hatched: central",
              title_fontsize=8)
    return _save(fig, out / filename)


def transport_bytes(data: Data, out: Path) -> Path | str:
    return _setting_bars(data, out, "wire_bytes", "wire", _kb, "kB on the wire", "Bytes per system",
                         "transport_bytes.png")


def transport_time(data: Data, out: Path) -> Path | str:
    return _setting_bars(data, out, "completion_s", "completion", float, "completion time (s)",
                         "Completion time per system", "transport_time.png")


def query_latency(data: Data, out: Path) -> Path | str:
    """p50 and p99 of remote-query latency per system, one marker per run, by loss."""
    systems = [s for s in data.systems() if any(r.system == s and r.query_p50_ms for r in data.rows)]
    if not systems:
        return "no query latencies"
    losses = sorted({r.loss_pct for r in data.rows})
    fig, axes = _panels(2, "Remote query latency per run (all settings)", width=6.0)
    markers = ["o", "s", "^", "D", "v"]
    for ax, column, label in ((axes[0], "query_p50_ms", "p50"), (axes[1], "query_p99_ms", "p99")):
        for k, loss in enumerate(losses):
            xs, ys = [], []
            for i, system in enumerate(systems):
                for r in data.rows:
                    if r.system == system and r.loss_pct == loss and getattr(r, column):
                        xs.append(i + (k - (len(losses) - 1) / 2) * 0.15)
                        ys.append(getattr(r, column))
            ax.scatter(xs, ys, marker=markers[k % len(markers)], label=f"{loss:g} % loss", alpha=0.75)
        ax.set_yscale("log")
        ax.set_xticks(range(len(systems)), systems, rotation=25, fontsize=8, ha="right")
        ax.set(ylabel=f"{label} latency (ms)", title=label)
        _legend(ax, 7)
    return _save(fig, out / "query_latency.png")


FIGURES: dict[str, Callable[[Data, Path], Path | str]] = {
    "fig06": fig6, "fig07": fig7, "fig08": fig8, "fig09": fig9, "fig10": fig10, "fig11": fig11,
    "fig12": fig12, "transport_bytes": transport_bytes, "transport_time": transport_time,
    "query_latency": query_latency,
}


def draw_all(rows: Iterable[BenchRow], outdir: Path) -> dict[str, Path | str]:
    """Every figure; values are written paths or the reason a figure was skipped."""
    outdir.mkdir(parents=True, exist_ok=True)
    data = Data(list(rows))
    return {name: fn(data, outdir) for name, fn in FIGURES.items()}


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.figures",
                                description="Figures from a coapkb benchmark CSV.")
    p.add_argument("csv", type=Path, nargs="?", default=ROOT / "experiments" / "results" / "quick.csv")
    p.add_argument("--outdir", type=Path, help="default: figures/ next to the CSV")
    args = p.parse_args(argv)
    rows = benchmark_rows(args.csv, "figures")
    if rows is None:
        return 1
    outdir = args.outdir or args.csv.parent / "figures"
    for name, result in draw_all(rows, outdir).items():
        if isinstance(result, Path):
            print(f"{name}: {result}")
        else:
            print(f"{name}: skipped ({result})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
