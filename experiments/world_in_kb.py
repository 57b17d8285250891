"""The world in the KB on slow lossy links: what writing every pick costs,
and whether every robot skips an object picked before.

    sudo .venv/bin/python -m experiments.world_in_kb costs      # 3 robots, 10 tasks, 35 kbit/s, 2 and 20 % (~10 min)
    sudo .venv/bin/python -m experiments.world_in_kb repeats    # 9 robots, 60 tasks, repeats in and across clusters
    .venv/bin/python -m experiments.world_in_kb report

Each run is one ``coapkb bench`` run (:func:`coapkb.bench.run.run_once`:
real processes, each robot in its own network namespace behind the
emulated link, OSCORE on), so the bytes are every link's.

* **costs**: the same tasks done by ``coap-distributed`` with a read-only
  KB, by ``coap-distributed`` writing every pick, position, load and
  charge (``--writable``), and by ``zmq-distributed`` (the paper's
  transport; it writes nothing), one after the other in each repetition so
  the three share the machine's state.  Per task: wire bytes over the tasks.
* **repeats**: 9 robots (three clusters of three, a writable KB replicated
  around the clusters) and 60 tasks: each cluster's first 10 objects are its
  own; of its last 10, five repeat its own first ones and five repeat the
  previous cluster's first ones, so a repeat comes 5-15 tasks after the
  pick it repeats.  From each run's record, for each object given twice:
  how the task that did not pick it ended (skipped as already picked, or
  not found at the shelf: its cluster decided before the pick's write
  reached it), whether both picked it (never: the world gives it to one),
  and the disagreements.

Writes ``costs.csv`` and ``repeats.csv`` (``BenchRow``, the bench's own
schema), ``repeats_tasks.csv`` (each repeat's fate) and ``table.md`` in
``--out`` (default ``experiments/results/world_in_kb/``).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from coapkb.bench import run as bench
from coapkb.bench.row import append_rows, read_rows
from coapkb.harness.team import DEFAULT_ONTOLOGIES, draw_tasks
from experiments.common import prepare_link_emulation, write_csv

ROOT = Path(__file__).resolve().parent.parent

DEFAULT_OUT = ROOT / "experiments" / "results" / "world_in_kb"
#: (label, system, writable)
COST_CASES = (("coap read-only", "coap-distributed", False), ("coap writing", "coap-distributed", True),
              ("zmq", "zmq-distributed", False))


def repeat_tasks(seed: int, clusters: int = 3, per_cluster: int = 20) -> list[str]:
    """Each cluster's share (split_tasks: contiguous): 10 own objects, then 5
    of them again and 5 of the previous cluster's (see the module docstring)."""
    fresh = per_cluster // 2
    drawn = draw_tasks(fresh * clusters, DEFAULT_ONTOLOGIES, seed=seed)
    firsts = [drawn[c * fresh:(c + 1) * fresh] for c in range(clusters)]
    tasks: list[str] = []
    for c in range(clusters):
        own, previous = firsts[c], firsts[(c - 1) % clusters]
        half = fresh // 2
        seconds = [x for pair in zip(own[:half], previous[half:]) for x in pair]
        tasks += own + seconds
    return tasks


async def run_costs(args: argparse.Namespace, out: Path) -> None:
    csv = out / "costs.csv"
    done = {(r.system, r.loss_pct, r.rep, r.kb_writable) for r in read_rows(csv)}
    for rep in range(args.reps):
        for loss in args.loss:
            for label, system, writable in COST_CASES:
                if (system, loss, rep, writable) in done:
                    continue
                row = await bench.run_once(system, 3, args.tasks, args.bandwidth, loss, rep, kb_writable=writable)
                append_rows(csv, [row])
                print(f"{label:15} {bench.format_row(row)}", flush=True)


async def run_repeats(args: argparse.Namespace, out: Path) -> None:
    csv = out / "repeats.csv"
    rows: list[dict] = []
    for rep in range(args.reps):
        tasks = repeat_tasks(seed=100 + rep)
        with tempfile.TemporaryDirectory(prefix="world-in-kb-") as tmp:
            row = await bench.run_once("coap-distributed", 9, len(tasks), args.bandwidth, args.repeat_loss, rep,
                                       seed=100 + rep, replication=2, kb_writable=True, task_list=tasks,
                                       trace_dir=Path(tmp))
            append_rows(csv, [row])
            print(f"repeats         {bench.format_row(row)}", flush=True)
            for record_file in Path(tmp).glob("*/record.json"):
                record = json.loads(record_file.read_text())
                rows += repeat_fates(record, rep)
    if rows:
        old = pd.read_csv(out / "repeats_tasks.csv").to_dict("records") if (out / "repeats_tasks.csv").exists() else []
        write_csv(out / "repeats_tasks.csv", list(rows[0]), old + rows)


def repeat_fates(record: dict, rep: int) -> list[dict]:
    """Each object given twice: which task picked it (its fate "assigned")
    and how the other ended (skipped, not found, or picked too)."""
    by_object: dict[str, list[dict]] = {}
    for task in record["tasks"]:
        if task.get("reassigned_from") is None:
            by_object.setdefault(task["object"], []).append(task)
    found = []
    for obj, tasks in by_object.items():
        if len(tasks) < 2:
            continue
        pickers = [t for t in tasks if t["fate"] in ("assigned", "reassigned")]
        others = [t for t in tasks if t not in pickers]
        other = others[0] if others else tasks[1]
        first = pickers[0] if pickers else tasks[0]
        found.append({
            "rep": rep, "object": obj, "cluster": other["cluster"], "seq": other["seq"],
            "picked_in_cluster": first["cluster"], "picked_at_seq": first["seq"],
            "same_cluster": first["cluster"] == other["cluster"],
            "fate": "picked twice" if len(pickers) > 1 else other["fate"],
            "skip_reason": other.get("skip_reason") or "", "not_found": other.get("not_found") or "",
            "agreed": all(t["agreed"] for t in tasks),
        })
    return found


def report(out: Path) -> str:
    lines = ["# The world in the KB", ""]
    costs = read_rows(out / "costs.csv")
    if costs:
        t = pd.DataFrame([r.to_dict() for r in costs])
        t["case"] = [f"{s.split('-')[0]}{' writing' if w else ''}" for s, w in zip(t.system, t.kb_writable)]
        t["bytes_per_task"] = t.wire_bytes / t.tasks
        cells = (t.groupby(["loss_pct", "case"]).agg(
            runs=("ok", "size"), ok=("ok", "sum"), bytes_per_task=("bytes_per_task", "median"),
            completion_s=("completion_s", "median"), disagreements=("tasks_disagreements", "sum"))
            .reset_index())
        zmq = cells[cells.case == "zmq"].set_index("loss_pct")
        cells["x_zmq_bytes"] = [round(b / zmq.bytes_per_task.get(loss), 2) for loss, b in
                                zip(cells.loss_pct, cells.bytes_per_task)]
        cells["x_zmq_time"] = [round(c / zmq.completion_s.get(loss), 2) for loss, c in
                               zip(cells.loss_pct, cells.completion_s)]
        link = f"{costs[0].robots} robots, {costs[0].tasks} tasks, {costs[0].bandwidth_kbps:g} kbit/s"
        lines += [f"## What writing every pick costs ({link})", "",
                  "Medians over the repetitions; `x_zmq`: against zmq-distributed at the same loss.", "",
                  cells.to_markdown(index=False, floatfmt="g"), ""]
    repeats_file = out / "repeats_tasks.csv"
    if repeats_file.exists():
        r = pd.read_csv(repeats_file)
        cells = (r.groupby("same_cluster").agg(
            repeats=("fate", "size"), skipped=("fate", lambda f: int((f == "skipped").sum())),
            not_found=("fate", lambda f: int((f == "not-found").sum())),
            picked_twice=("fate", lambda f: int((f == "picked twice").sum())),
            disagreed=("agreed", lambda a: int((~a.astype(bool)).sum())))
            .reset_index())
        cells["where"] = ["same cluster" if s else "another cluster" for s in cells.same_cluster]
        runs = read_rows(out / "repeats.csv")
        link = f"9 robots, {runs[0].tasks if runs else '?'} tasks, {runs[0].bandwidth_kbps:g} kbit/s, " \
               f"{runs[0].loss_pct:g} % loss" if runs else ""
        lines += [f"## Repeated objects ({link})", "",
                  "Each object given twice: how the task that did not pick it ended.", "",
                  cells[["where", "repeats", "skipped", "not_found", "picked_twice", "disagreed"]]
                  .to_markdown(index=False), "",
                  f"Runs: {len(runs)}, disagreements over all their tasks: "
                  f"{sum(x.tasks_disagreements or 0 for x in runs)}.", ""]
    return "\n".join(lines)


async def amain(args: argparse.Namespace) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    if args.what in ("costs", "repeats"):
        why = prepare_link_emulation()
        if why is not None:
            print(f"world_in_kb: no kernel link emulation here: {why}", file=sys.stderr)
            return 2
        await (run_costs if args.what == "costs" else run_repeats)(args, out)
    text = report(out)
    (out / "table.md").write_text(text + "\n")
    print(text)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m experiments.world_in_kb",
                                description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("what", choices=("costs", "repeats", "report"))
    p.add_argument("--tasks", type=int, default=10, help="tasks of a costs run (default 10)")
    p.add_argument("--bandwidth", type=float, default=35.0, metavar="KBPS")
    p.add_argument("--loss", type=float, nargs="+", default=[2.0, 20.0], metavar="PCT", help="costs: losses")
    p.add_argument("--repeat-loss", type=float, default=2.0, metavar="PCT", help="repeats: the loss (default 2)")
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    return asyncio.run(amain(build_parser().parse_args(argv)))


if __name__ == "__main__":
    sys.exit(main())
