"""``experiments/results/report.md`` from a benchmark CSV: setup, commands,
key ratios next to the seed paper's, tables, figures and notes.

    .venv/bin/python -m experiments.report experiments/results/quick.csv

Every number is computed from the CSV; nothing is typed in by hand except the
seed's own figures (its ~42 % byte saving).  Ratios compare two systems only
on *paired* runs -- the same robots, tasks, bandwidth, loss and repetition
(hence the same task list, seeded by the repetition) -- and are summarised by
the median of the per-pair ratios with a distribution-free 95 % interval and
their range, so one slow outlier cannot dominate.  Per-cell numbers are medians
over the repetitions with the same kind of interval (``experiments/stats.py``);
the aggregation is pandas.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import platform
import sys
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from coapkb.bench.run import SYSTEMS, BenchRow
from experiments import matrix_time
from experiments.common import benchmark_rows
from experiments.stats import CONFIDENCE, SHORT, Estimate, median_ci, ratio_ci

ROOT = Path(__file__).resolve().parent.parent

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


#: A cell of the matrix; a cell and a repetition (SETTING) make two runs a pair.
CELL = ("robots", "tasks", "bandwidth_kbps", "loss_pct")


#: Appended to a system's name for its runs without the team's keys, where
#: the same results also hold secured runs of it (``coapkb bench
#: --insecure`` beside the default): a system of its own in every table and
#: pairing, never mixed with the secured runs of the same cell.
INSECURE = " --insecure"


def system_labels(rows: Sequence[BenchRow]) -> list[str]:
    """Each row's system, marked :data:`INSECURE` when it ran plain and
    ``rows`` also hold secured runs of that system (results from before the
    security column are all plain: their names stay)."""
    secured = {r.system for r in rows if r.security != "none"}
    return [r.system + INSECURE if r.security == "none" and r.system in secured else r.system for r in rows]


def frame(rows: Sequence[BenchRow]) -> pd.DataFrame:
    """The rows as a data frame, one column per CSV column (None as NaN),
    with the systems named by :func:`system_labels`."""
    df = pd.DataFrame([r.to_dict() for r in rows], columns=list(BenchRow.__dataclass_fields__))
    df["system"] = system_labels(rows)
    return df


@dataclass(frozen=True)
class Pairs:
    """Systems ``a`` and ``b`` side by side, one line per setting (cell and
    repetition) where both have an ok row; ``wide`` has columns ``(column, system)``."""

    a: str
    b: str
    wide: pd.DataFrame

    def __len__(self) -> int:
        return len(self.wide)

    def values(self, column: str, system: str) -> np.ndarray:
        return self.wide[(column, system)].to_numpy(dtype=float)

    def ratio(self, column: str) -> Estimate | None:
        """The median of the per-pair ratios ``a/b`` of ``column`` with its interval."""
        if not len(self):
            return None
        return ratio_ci(self.values(column, self.a), self.values(column, self.b))


def paired(df: pd.DataFrame, a: str, b: str, where: Callable[[pd.DataFrame], Any] | None = None) -> Pairs:
    """``a`` and ``b`` on every setting where both have an ok row and the
    boolean mask ``where(df)`` holds.  A setting run under several profiles
    keeps its last row, as the CSV's resume logic does."""
    ok = df[df["ok"].astype(bool) & df["system"].isin((a, b))]
    if where is not None:
        ok = ok[where(ok)]
    wide = ok.drop_duplicates([*SETTING, "system"], keep="last").set_index([*SETTING, "system"]).unstack("system")
    present = set(wide.columns.get_level_values(1)) if not wide.empty else set()
    if a == b or not {a, b} <= present:
        return Pairs(a, b, pd.DataFrame())
    both = wide[("ok", a)].notna() & wide[("ok", b)].notna()
    return Pairs(a, b, wide[both].sort_index())


def ratio(pairs: Pairs, column: str) -> Estimate | None:
    return pairs.ratio(column)


def _fmt(r: Estimate | None, saving: bool = False) -> str:
    """A/B as ``x0.62 [0.58, 0.66] (n=39)``; as a saving (1 - A/B) ``38 % [34, 42] (n=39)``."""
    if r is None:
        return "no paired runs"
    if saving:
        s = r.complement().map(lambda v: 100 * v)
        interval = f" [{s.low:.0f}, {s.high:.0f}]{SHORT if s.short else ''}" if s.has_interval else ""
        return f"{s.value:.0f} %{interval} (n={s.n})"
    interval = f" [{r.low:.2f}, {r.high:.2f}]{SHORT if r.short else ''}" if r.has_interval else ""
    return f"x{r.value:.2f}{interval} (n={r.n})"


def interval_note(what: str = "Medians") -> str:
    """The one sentence every table with intervals carries."""
    return (f"{what} with distribution-free {CONFIDENCE:.0%} intervals `[low, high]` from order statistics "
            f"(`experiments/stats.py`); with fewer than 6 values no such interval exists, and the range of the values "
            f"is shown instead, marked {SHORT} (it covers the median with probability 1 - 2^(1-n): 75 % for 3 runs); "
            "`(n=1)`: a single run, no interval.")


def _kb(v: Any) -> str:
    return "-" if v is None else f"{v / 1000:.1f}"


def _s(v: Any) -> str:
    return "-" if v is None else f"{v:.1f}"


def _md_table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return lines


def _systems(rows: Sequence[BenchRow]) -> list[str]:
    """The systems of ``rows`` in :data:`SYSTEMS`' order, each insecure variant after its system."""
    present = set(system_labels(rows))
    return [label for s in SYSTEMS for label in (s, s + INSECURE) if label in present]


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
    security = frame(rows).groupby("system")["security"].agg(lambda v: ", ".join(sorted(set(v))))
    lines += _md_table(("system", "what", "security"),
                       ((f"`{s}`", SYSTEMS[s.removesuffix(INSECURE)].description, security.get(s, "none"))
                        for s in _systems(rows)))
    lines += ["", "Security as in `coapkb team` (the bench's default): `oscore` = OSCORE keyed by EDHOC, `curve` = "
              "CurveZMQ, `tls` = Zenoh's mutual TLS, each from the team's keys with its handshakes counted; "
              "the seed's systems run plain, as the seed ran them (docs/security.md)."]
    return lines


def section_commands(csv_path: Path, profile: str) -> list[str]:
    rel = _rel(csv_path)
    return [
        "## Commands",
        "",
        "```sh",
        "make venv                                                   # once",
        f"sudo .venv/bin/python -m experiments.sweep --profile {profile}      # resumable; --jobs N runs N at once",
        "# or on a Dask cluster (docs/benchmarks.md, \"Running on a cluster\"):",
        f".venv/bin/python -m experiments.sweep --profile {profile} --engine dask://HOST:8786",
        f".venv/bin/python -m experiments.figures {rel}",
        f".venv/bin/python -m experiments.report {rel}",
        "# one run by hand:",
        "sudo .venv/bin/coapkb bench --robots 3 --tasks 5 --bandwidth 35 --loss 2 \\",
        "    --systems coap-distributed,coap-central,zmq-distributed,zmq-central --out /tmp/bench.csv",
        "```",
        "",
        "Details and definitions: [`docs/benchmarks.md`](../../docs/benchmarks.md).",
    ]


def key_ratios(rows: Sequence[BenchRow]) -> list[tuple[str, str, str, str]]:
    """(comparison, bytes, completion time, the seed's number) rows."""
    df = frame(rows)
    out: list[tuple[str, str, str, str]] = []
    for label, dist, cent in (
        ("seed stack (ZeroMQ, SPARQL + JSON)", "seed-distributed", "seed-central"),
        ("CoAP + compact", "coap-distributed", "coap-central"),
        ("ZeroMQ + compact", "zmq-distributed", "zmq-central"),
        ("Zenoh + compact", "zenoh-distributed", "zenoh-central"),
    ):
        pairs = paired(df, dist, cent)
        if len(pairs):
            out.append((f"distributed vs central, {label}: saving", _fmt(pairs.ratio("wire_bytes"), True),
                        _fmt(pairs.ratio("completion_s"), True), f"~{SEED_BYTE_SAVING:.0%} fewer bytes; faster"))
    for label, a, b, seed in COMPARISONS:
        pairs = paired(df, a, b)
        if len(pairs):
            out.append((f"{label}: A/B", _fmt(pairs.ratio("wire_bytes")), _fmt(pairs.ratio("completion_s")), seed))
    return out


#: Paired comparisons beyond distributed vs central: (label, A, B, the seed's number).
COMPARISONS: tuple[tuple[str, str, str, str], ...] = (
    ("CoAP vs ZeroMQ, distributed (both compact)", "coap-distributed", "zmq-distributed", "-"),
    ("CoAP vs ZeroMQ, central (both compact)", "coap-central", "zmq-central", "-"),
    ("CoAP vs Zenoh, distributed (both compact)", "coap-distributed", "zenoh-distributed", "-"),
    ("CoAP vs Zenoh, central (both compact)", "coap-central", "zenoh-central", "-"),
    ("Zenoh vs ZeroMQ, distributed (both compact)", "zenoh-distributed", "zmq-distributed", "-"),
    ("compact vs seed wire (ZeroMQ, distributed)", "zmq-distributed", "seed-distributed", "-"),
    ("compact vs seed wire (ZeroMQ, central)", "zmq-central", "seed-central", "-"),
    ("coapkb (CoAP, compact, distributed) vs the seed's system", "coap-distributed", "seed-distributed", "-"),
    ("CoAP vs Zenoh/QUIC, distributed (both secured)", "coap-distributed", "zenoh-quic-distributed", "-"),
    ("CoAP vs Zenoh reliable UDP, distributed (CoAP secured, Zenoh plain)", "coap-distributed",
     "zenoh-udp-distributed", "-"),
    ("CoAP vs DDS, distributed (both plain)", "coap-distributed" + INSECURE, "dds-distributed", "-"),
    ("CoAP vs DDS, central (both plain)", "coap-central" + INSECURE, "dds-central", "-"),
)
#: The per-cell ratio tables: (column header, A, B).
CELL_RATIOS: tuple[tuple[str, str, str], ...] = (
    ("CoAP dist/central", "coap-distributed", "coap-central"),
    ("ZeroMQ dist/central", "zmq-distributed", "zmq-central"),
    ("seed dist/central", "seed-distributed", "seed-central"),
    ("CoAP/ZeroMQ dist", "coap-distributed", "zmq-distributed"),
    ("CoAP/ZeroMQ central", "coap-central", "zmq-central"),
    ("CoAP/Zenoh dist", "coap-distributed", "zenoh-distributed"),
    ("CoAP/Zenoh central", "coap-central", "zenoh-central"),
    ("CoAP/Zenoh-QUIC dist", "coap-distributed", "zenoh-quic-distributed"),
    ("CoAP/Zenoh-rel-UDP dist", "coap-distributed", "zenoh-udp-distributed"),
    ("CoAP/DDS dist (plain)", "coap-distributed" + INSECURE, "dds-distributed"),
)


def section_ratios(rows: Sequence[BenchRow]) -> list[str]:
    lines = [
        "## Key ratios",
        "",
        "Paired runs only (same robots, tasks, bandwidth, loss and repetition, hence the same tasks). "
        "\"saving\" = 1 - A/B (positive: the first system uses less); \"A/B\" = median of the per-pair ratios "
        f"with its {CONFIDENCE:.0%} interval and the number of pairs. " + interval_note("Ratios are medians"),
        "",
    ]
    table = key_ratios(rows)
    if not table:
        return lines + ["No paired runs: the CSV has fewer than two systems per setting."]
    lines += _md_table(("comparison", "bytes on the wire", "completion time", "seed paper"), table)
    df = frame(rows)

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
                    pairs = paired(df, dist, cent, lambda d, want=want: (  # type: ignore[misc]
                        (d.bandwidth_kbps == want[0]) & (d.tasks == want[1]) & (d.loss_pct == want[2])
                        & (d.robots == want[3])))
                    r = pairs.ratio("wire_bytes")
                    if r is not None:
                        saving = _fmt(r, saving=True).rsplit(" (", 1)[0]  # the pairs have their own column
                        head.append((dist.split("-")[0], robots, _g(loss), saving, r.n))
        if head:
            lines += ["", f"Distributed vs central byte saving in the seed's Fig. 6 setting ({_g(bw)} kbit/s, {t} tasks); "
                      f"the seed reports ~{SEED_BYTE_SAVING:.0%} at 2 % loss and about the same at 20 %:", ""]
            lines += _md_table(("stack", "robots", "loss %", "saving", "pairs"), head)

    # CoAP vs ZeroMQ by loss: where the time ratio flips.
    by_loss = []
    for loss in losses:
        for a, b in (("coap-distributed", "zmq-distributed"), ("coap-central", "zmq-central")):
            pairs = paired(df, a, b, lambda d, loss=loss: d.loss_pct == loss)  # type: ignore[misc]
            rb, rt = pairs.ratio("wire_bytes"), pairs.ratio("completion_s")
            if rb and rt:
                by_loss.append((_g(loss), f"{a} / {b}", _fmt(rb).rsplit(" (", 1)[0], _fmt(rt).rsplit(" (", 1)[0], rb.n))
    if by_loss:
        lines += ["", "CoAP vs ZeroMQ by loss level (A/B, median of the paired settings' ratios):", ""]
        lines += _md_table(("loss %", "A / B", "bytes", "completion time", "pairs"), by_loss)
    return lines


def cell_estimates(df: pd.DataFrame, column: str) -> pd.DataFrame:
    """Per cell (rows) and system (columns): the :class:`Estimate` of ``column``
    over the ok repetitions (None where there are none), and the failed runs
    as a second column level ``failed``."""
    ok = df[df["ok"].astype(bool)]
    est = ok.groupby([*CELL, "system"])[column].agg(lambda s: median_ci(s.to_numpy(dtype=float)))
    failed = df[~df["ok"].astype(bool)].groupby([*CELL, "system"]).size()
    both = pd.DataFrame({"estimate": est, "failed": failed})
    both["failed"] = both["failed"].fillna(0).astype(int)
    return both.unstack("system").sort_index()


def section_tables(rows: Sequence[BenchRow]) -> list[str]:
    systems = _systems(rows)
    df = frame(rows)
    lines = ["## Results", "", interval_note("Medians over the repetitions of the ok runs") +
             " \"failed\" runs are listed above.", ""]
    for title, column, fmt in (
        ("Bytes on the wire (kB)", "wire_bytes", lambda v: f"{v / 1000:.1f}"),
        ("Task completion time (s)", "completion_s", lambda v: f"{v:.1f}"),
        ("Retransmissions (CoAP: retransmitted CONs; ZeroMQ: TCP RetransSegs)", "retransmissions", lambda v: f"{v:.0f}"),
        ("Remote query latency p99 (ms)", "query_p99_ms", lambda v: f"{v:.0f}"),
    ):
        table = cell_estimates(df, column)

        def cell(key: tuple[Any, ...], system: str, fmt: Callable[[float], str] = fmt,
                 table: pd.DataFrame = table) -> str:
            est = table["estimate"].get(system, pd.Series(dtype=object)).get(key)
            bad = table["failed"].get(system, pd.Series(dtype=float)).get(key)
            bad = 0 if bad is None or pd.isna(bad) else int(bad)
            text = est.format(fmt) if isinstance(est, Estimate) else "-"
            return text + (f" ({bad} failed)" if bad else "")

        lines += [f"### {title}", ""]
        lines += _md_table(
            ("robots", "tasks", "kbit/s", "loss %", *systems),
            ((k[0], k[1], _g(k[2]), _g(k[3]), *(cell(k, s) for s in systems)) for k in table.index),
        )
        lines.append("")
    lines += section_cell_ratios(df)
    return lines


def section_cell_ratios(df: pd.DataFrame) -> list[str]:
    """Per cell, the paired ratios A/B over its repetitions, for bytes and completion time."""
    present = set(df["system"])
    columns = [(h, a, b) for h, a, b in CELL_RATIOS if {a, b} <= present]
    if not columns:
        return []
    lines = ["### Paired ratios per cell (A/B)", "",
             interval_note("Medians of the per-repetition ratios") + " Bytes first, then completion time.", ""]
    for title, column in (("bytes on the wire", "wire_bytes"), ("completion time", "completion_s")):
        per: dict[str, pd.Series] = {}
        for header, a, b in columns:
            pairs = paired(df, a, b)
            if not len(pairs):
                continue
            per[header] = pairs.wide.groupby(level=list(CELL)).apply(
                lambda w, a=a, b=b, column=column: ratio_ci(w[(column, a)].to_numpy(dtype=float),
                                             w[(column, b)].to_numpy(dtype=float)))
        if not per:
            continue
        table = pd.DataFrame(per).sort_index()
        lines += [f"#### {title}", ""]
        lines += _md_table(
            ("robots", "tasks", "kbit/s", "loss %", *table.columns),
            ((k[0], k[1], _g(k[2]), _g(k[3]),
              *((v.format(lambda x: f"{x:.2f}") if isinstance(v, Estimate) else "-") for v in table.loc[k]))
             for k in table.index),
        )
        lines.append("")
    return lines


def section_figures(figdir: Path, report_dir: Path) -> list[str]:
    present = [name for name in FIGURE_TITLES if (figdir / name).exists()]
    if not present:
        return ["## Figures", "", "No figures yet: run `.venv/bin/python -m experiments.figures` first."]
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
        "Why (packet traces, kernel counters, the failure modes): the reports listed in "
        "[`docs/results.md`](../../docs/results.md); for Zenoh, "
        "[`docs/reports/2026-11-23-zenoh.md`, \"Where each wins and loses, and why\"]"
        "(../../docs/reports/2026-11-23-zenoh.md#where-each-wins-and-loses-and-why).",
        "",
    ]
    df = frame(rows)
    for label, a, b in (
        ("Distribution (CoAP)", "coap-distributed", "coap-central"),
        ("Distribution (ZeroMQ)", "zmq-distributed", "zmq-central"),
        ("Distribution (seed stack)", "seed-distributed", "seed-central"),
        ("CoAP over ZeroMQ (distributed)", "coap-distributed", "zmq-distributed"),
        ("CoAP over ZeroMQ (central)", "coap-central", "zmq-central"),
        ("Compact wire over the seed's (ZeroMQ, distributed)", "zmq-distributed", "seed-distributed"),
        ("Distribution (Zenoh)", "zenoh-distributed", "zenoh-central"),
        ("CoAP over Zenoh (distributed)", "coap-distributed", "zenoh-distributed"),
        ("CoAP over Zenoh (central)", "coap-central", "zenoh-central"),
        ("Zenoh over ZeroMQ (distributed)", "zenoh-distributed", "zmq-distributed"),
    ):
        pairs = paired(df, a, b)
        if not len(pairs):
            continue
        w = pairs.wide
        fewer = int((w[("wire_bytes", a)] < w[("wire_bytes", b)]).sum())
        slowdown = w[("completion_s", a)] / w[("completion_s", b)]
        faster = int((slowdown < 1).sum())
        text = (f"- **{label}**: fewer bytes in {fewer} of {len(pairs)} paired settings, "
                f"faster in {faster} of {len(pairs)}.")
        if (slowdown >= 1).any():
            robots, tasks, bw, loss, rep = slowdown[slowdown >= 1].idxmax()
            pair = w.loc[(robots, tasks, bw, loss, rep), "completion_s"]
            x, y = pair[a], pair[b]
            text += (f" Largest slow-down x{x / y:.1f} at {robots} robots, "
                     f"{tasks} tasks, {_g(bw)} kbit/s, {_g(loss)} % loss "
                     f"({x:.1f} s vs {y:.1f} s).")
        lines.append(text)
    for transport, name in (("zmq", "ZeroMQ"), ("zenoh", "Zenoh")):
        tcp = [r for r in rows if r.transport == transport and r.tcp_aborts is not None]
        if not tcp:
            continue
        aborted = [r for r in tcp if r.tcp_aborts > 0]
        lines.append(
            f"- **{name} connections given up by the kernel** (`tcp_aborts` > 0): {len(aborted)} of {len(tcp)} "
            f"{name} runs; {sum(1 for r in aborted if not r.ok)} of those failed, against "
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
        _reps_caveat(rows),
        "- Repetitions: a run's task list is drawn from the seed 1 + rep (column `seed`), so the systems of one "
        "cell and repetition do the same tasks (the pair of the ratios); which packets the link drops is the "
        "kernel's random draw, not seeded.",
    ]
    return lines


def _reps_caveat(rows: Sequence[BenchRow]) -> str:
    reps = frame(rows).groupby([*CELL, "system"])["rep"].nunique()
    low, high = (int(reps.min()), int(reps.max())) if len(reps) else (0, 0)
    count = f"{low}" if low == high else f"{low} to {high}"
    text = f"- {count} repetition{'s' if high > 1 else ''} per cell: loss is random, so single-run times at high loss "
    text += "vary by tens of percent (a few unlucky retransmission back-offs dominate); bytes vary much less."
    if low < 6:
        text += (f" Fewer than 6 repetitions cannot give a {CONFIDENCE:.0%} distribution-free interval for a "
                 f"median: the intervals marked {SHORT} are the range of the runs.")
    return text


# --------------------------------------------------------------------------- the paper matrix's duration

#: The machine counts the duration table shows.
MACHINES = (1, 4, 16, 64)
CONCURRENCY_CSV = ROOT / "experiments" / "results" / "concurrency.csv"


def _duration(seconds: float) -> str:
    """``3.2 h``, ``2.1 d (51 h)``, ``12 min``."""
    hours = seconds / 3600
    if hours >= 48:
        return f"{hours / 24:.1f} d ({hours:.0f} h)"
    if hours >= 1:
        return f"{hours:.1f} h"
    return f"{seconds / 60:.0f} min"


def two_at_once_ratio(path: Path = CONCURRENCY_CSV) -> tuple[float, str]:
    """``(wall of a list run two at once / one at a time, where it comes from)``,
    from ``experiments/concurrency.py``'s CSV; 0.5 (ideal) without it."""
    try:
        walls = pd.read_csv(path).groupby("jobs")["list_wall_s"].first()
        return float(walls[2] / walls[1]), f"`{_rel(path)}`: {walls[1]:.1f} s one at a time, {walls[2]:.1f} s two at once"
    except (OSError, KeyError, ValueError, pd.errors.ParserError):
        return 0.5, "no concurrency measurement found: ideal halving assumed"


@dataclass(frozen=True)
class PaperTime:
    """The paper profile's predicted duration from the measured rows' wall times."""

    model: matrix_time.TimeModel
    time: matrix_time.MatrixTime
    runs: int
    #: Measured rows with a wall time, and failed ones among them.
    fitted: int
    failed: int
    unmeasured_wall: int
    in_sample_error: float
    held_out_error: float
    #: Held-out predicted sum over measured sum.
    held_out_bias: float
    #: Mean runs at once in the measured sweep, and what that is taken as (1 or 2).
    concurrency: float
    measured_at: int
    ratio2: float
    ratio2_source: str
    one_at_once_s: float
    two_at_once_s: float
    #: Share of the plan's predicted time in cells the data has, and beyond the measured ranges.
    measured_share: float
    beyond_share: float
    #: Per axis beyond the measured range, its share of the predicted time (a run can be beyond on two).
    beyond_axes: dict[str, float]

    def makespans(self) -> pd.DataFrame:
        """Rows: machines; columns: one and two runs at once per machine."""
        n = np.asarray(MACHINES, dtype=float)
        return pd.DataFrame({"1 at once": np.maximum(self.one_at_once_s / n, self.time.longest_s),
                             "2 at once": np.maximum(self.two_at_once_s / n, self.time.longest_s)},
                            index=pd.Index(MACHINES, name="machines"))

    def line(self) -> str:
        m = self.makespans()
        return (f"paper matrix ({self.runs} runs): {_duration(self.one_at_once_s)} on one machine one run at a time, "
                f"{_duration(self.two_at_once_s)} two at once; "
                + ", ".join(f"{n} machines {_duration(m.loc[n, '2 at once'])}" for n in MACHINES[1:])
                + f" (held-out cell error {self.held_out_error:.0%}, {self.beyond_share:.0%} of the time extrapolated)")


def _walls(rows: Sequence[BenchRow]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """All rows as a frame, and those with a wall time."""
    df = frame(rows)
    return df, df[df["wall_s"].notna() & (df["wall_s"] > 0)]


def no_paper_time(rows: Sequence[BenchRow]) -> str | None:
    """Why :func:`paper_time` has nothing to say about these rows, or None
    if it has: no wall times, or one cell only (a ``coapkb bench`` CSV), from
    which no axis of the matrix can be fitted and no cell held out."""
    _, walls = _walls(rows)
    if walls.empty:
        return "no run in this CSV has a wall time (`wall_s`): nothing to estimate from"
    cells = len(walls.groupby(list(CELL)))
    if cells < 2:
        return (f"the runs of this CSV with a wall time cover {cells} cell (robots, tasks, bandwidth, loss): "
                "too few to fit how a run's time grows along the matrix; a sweep's CSV covers many")
    return None


def paper_time(rows: Sequence[BenchRow], profile: str = "paper") -> PaperTime | None:
    """The model fitted to ``rows`` and applied to every run of ``profile``
    (``sweep.plan``, the default ``robust`` CoAP profile); None without wall
    times or with one cell only (:func:`no_paper_time` says which)."""
    from experiments import sweep  # experiments/sweep.py: the plan and each run's kill limit

    if no_paper_time(rows) is not None:
        return None
    df, walls = _walls(rows)
    runs = sweep.plan(sweep.PROFILES[profile])
    plan = pd.DataFrame({"system": [r.system for r in runs], "robots": [r.robots for r in runs],
                         "tasks": [r.tasks for r in runs], "bandwidth_kbps": [r.bandwidth for r in runs],
                         "loss_pct": [r.loss for r in runs]})
    cap = np.array([sweep.limit_for(r) for r in runs])
    model = matrix_time.fit(walls)
    time = matrix_time.matrix_time(model, plan, cap)
    held = matrix_time.held_out_predictions(walls)
    measured = walls.loc[held.index, "wall_s"].to_numpy(dtype=float)
    conc = matrix_time.concurrency(walls)
    at = 2 if conc >= 1.5 else 1
    ratio2, source = two_at_once_ratio()
    # The predictions are walls as measured: at `at` runs at once.
    one = time.total_s if at == 1 else time.total_s / 2 / ratio2
    two = time.total_s * ratio2 if at == 1 else time.total_s / 2
    pred = pd.Series(model.predict(plan, cap))
    cells = set(map(tuple, walls[list(CELL)].astype(float).itertuples(index=False)))
    in_data = pd.Series([c in cells for c in map(tuple, plan[list(CELL)].astype(float).itertuples(index=False))])
    beyond_masks = {
        "tasks > " + _g(walls["tasks"].max()): plan["tasks"] > walls["tasks"].max(),
        "bandwidth > " + _g(walls["bandwidth_kbps"].max()) + " kbit/s": plan["bandwidth_kbps"] > walls["bandwidth_kbps"].max(),
        "bandwidth < " + _g(walls["bandwidth_kbps"].min()) + " kbit/s": plan["bandwidth_kbps"] < walls["bandwidth_kbps"].min(),
        "loss > " + _g(walls["loss_pct"].max()) + " %": plan["loss_pct"] > walls["loss_pct"].max(),
        "robots > " + _g(walls["robots"].max()): plan["robots"] > walls["robots"].max(),
    }
    beyond = pd.concat(beyond_masks, axis=1)
    axes = {name: float(pred[mask].sum() / pred.sum()) for name, mask in beyond_masks.items() if mask.any()}
    return PaperTime(
        model=model, time=time, runs=len(plan), fitted=len(walls), failed=int((~walls["ok"].astype(bool)).sum()),
        unmeasured_wall=len(df) - len(walls),
        in_sample_error=float(np.median(matrix_time.abs_errors(model, walls))),
        held_out_error=float(np.median(np.abs(held.to_numpy() - measured) / measured)),
        held_out_bias=float(held.sum() / measured.sum()), concurrency=conc, measured_at=at,
        ratio2=ratio2, ratio2_source=source, one_at_once_s=one, two_at_once_s=two,
        measured_share=float(pred[in_data].sum() / pred.sum()),
        beyond_share=float(pred[beyond.any(axis=1)].sum() / pred.sum()), beyond_axes=axes,
    )


def section_matrix_time(rows: Sequence[BenchRow], profile: str = "paper") -> list[str]:
    """How long the ``paper`` profile takes, on one machine and on N, from these runs' wall times."""
    lines = ["## How long the paper matrix takes", ""]
    est = paper_time(rows, profile)
    if est is None:
        why = no_paper_time(rows) or "nothing to estimate from"
        return lines + [f"Not estimated: {why}."]
    coef = est.model.coef
    lines += [
        f"Predicted from the {est.fitted} runs of this CSV with a wall time (`wall_s`: a run's whole time, set-up "
        f"and teardown included; failed runs count too, a failed run costs its time: {est.failed} here"
        + (f"; {est.unmeasured_wall} runs without a wall time are left out" if est.unmeasured_wall else "")
        + f"), applied to all {est.runs} runs of the `{profile}` profile (`sweep.plan`, {len(est.time.by_system)} "
        "systems, every repetition). The model (`experiments/matrix_time.py`), per system, least squares:",
        "",
        "    wall = setup + per_robot x (robots - 3)",
        "         + k x (per_task + serial x (35 / kbit/s - 1) + per_loss x (loss % - 2)),  k = ceil(tasks / (robots // 3))",
        "",
        "`k` is the tasks one cluster does in sequence; `serial` scales with 1/bandwidth (serialisation), so 128 kbit/s "
        "is interpolated between 35 and 256 and 512 lies just beyond 256; time is linear in loss between the measured "
        "levels and in robots (6 between 3 and 9). A coefficient a system's own runs cannot determine (its runs do "
        "not vary that axis) is taken from the pooled fit of all systems (one setup each, the rest shared); a system "
        "with no runs gets the pooled values, and a coefficient no run determines even pooled (e.g. `per_robot` when all "
        "runs have 3 robots) is 0. No run is predicted below 1 s or above the "
        "sweep's kill limit for it (`sweep.limit_for`).",
        "",
        f"**Uncertainty.** Median absolute error of the fit on its own runs: {est.in_sample_error:.0%}; on a cell "
        f"(robots, tasks, bandwidth, loss) left out of the fit and predicted: **{est.held_out_error:.0%}**, and the "
        f"left-out predictions sum to x{est.held_out_bias:.2f} the measured time. Only "
        f"{est.measured_share:.0%} of the predicted time is in cells this CSV measured; "
        f"**{est.beyond_share:.0%} is extrapolated beyond the measured ranges** ("
        + ("; ".join(f"{name}: {share:.0%}" for name, share in est.beyond_axes.items()) or "none") + "), "
        "and the rest (the 5-15 % loss levels, 128 kbit/s, 6 robots, and measured levels in combinations "
        "not measured, e.g. 20 % loss at 256 kbit/s or 20 tasks) is interpolated along straight lines "
        "through few points. Read the totals as the order of magnitude, not to the hour: high loss "
        "times are skewed by a few long back-offs and ZeroMQ hangs up to a query timeout.",
        "",
        f"**Runs at once.** The measured runs ran {est.concurrency:.1f} at a time on average (sum of their wall "
        f"times over the sweep's span), so their times are taken as {est.measured_at} at once. Two at once on a "
        f"2-core machine takes x{est.ratio2:.2f} the wall time of one at a time ({est.ratio2_source}; "
        "docs/benchmarks.md, \"Running on a cluster\").",
        "",
        f"On N such machines: the ideal division of the work, never below the longest single run "
        f"({_duration(est.time.longest_s)}).",
        "",
    ]
    spans = est.makespans()
    lines += _md_table(("machines", "one run at a time", "two at once (the tested setting)"),
                       ((n, _duration(spans.loc[n, "1 at once"]), _duration(spans.loc[n, "2 at once"]))
                        for n in spans.index))
    lines += ["", "Per system (predicted run time summed over its runs, as measured, and the fitted coefficients in "
              "seconds; \"borrowed\": from the pooled fit):", ""]
    share = est.time.by_system / est.time.total_s
    lines += _md_table(
        ("system", "runs", "run time", "share", *matrix_time.FEATURES, "borrowed"),
        ((f"`{s}`", est.time.runs_by_system[s], _duration(est.time.by_system[s]), f"{share[s]:.0%}",
          *((f"{coef.loc[s, f]:.2f}" if s in coef.index else f"({est.model.pooled[f]:.2f})")
            for f in matrix_time.FEATURES),
          ", ".join(est.model.borrowed.get(s, ())) if s in coef.index else "all (no runs)")
         for s in est.time.by_system.sort_values(ascending=False).index),
    )
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
        "agent over ZeroMQ/TCP and over Zenoh/TCP, and the seed's own wire format. Generated by "
        "`.venv/bin/python -m experiments.report`.",
        "",
    ]
    for section in (
        section_setup(rows, csv_path, profile),
        section_commands(csv_path, profile),
        section_ratios(rows),
        section_notes(rows),
        section_tables(rows),
        section_matrix_time(rows),
        section_figures(figdir, report_path.parent),
    ):
        lines += section + [""]
    return "\n".join(lines).rstrip() + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.report",
                                description="Markdown report from a coapkb benchmark CSV.")
    p.add_argument("csv", type=Path, nargs="?", default=ROOT / "experiments" / "results" / "quick.csv")
    p.add_argument("--out", type=Path, help="default: report.md next to the CSV")
    p.add_argument("--figures", type=Path, help="figure directory (default: figures/ next to the CSV)")
    p.add_argument("--profile", help="profile name for the title (default: the CSV's name)")
    args = p.parse_args(argv)
    rows = benchmark_rows(args.csv, "report")
    if rows is None:
        return 1
    out = args.out or args.csv.parent / "report.md"
    figdir = args.figures or args.csv.parent / "figures"
    out.write_text(build_report(rows, args.csv, figdir, out, args.profile), encoding="utf-8")
    print(f"report written to {out}")
    estimate = paper_time(rows)
    if estimate is not None:
        print(estimate.line())
    else:
        print(f"paper matrix time not estimated: {no_paper_time(rows)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
