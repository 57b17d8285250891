"""A picture of a recorded run, drawn from its MCAP file alone.

    .venv/bin/coapkb team --robots 3 --tasks 30 --writable --record /tmp/run.mcap --quiet
    .venv/bin/python -m experiments.mcap_picture /tmp/run.mcap --out docs/figures/run.png

Left, the warehouse seen from above: its racks, charging docks and the depot
(the geometry from the recording's metadata and the KB it names) and each
robot's track, as the feeder observed it (``/robots/state``); right, over
the run's time, each robot's jobs done and its battery (``/robots/state``),
and each task's fate when it was decided (``/tasks``).  The same channels
Foxglove shows (``examples/foxglove-layout.json``); a viewer is a desktop
or web app, so the README shows this instead.
"""

from __future__ import annotations

import argparse
import json
import sys
import textwrap
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from mcap.reader import make_reader

from coapkb.harness.recording import warehouse
from coapkb.world import Position

ROOT = Path(__file__).resolve().parent.parent

FATE_MARKS = {"assigned": ("o", "tab:green"), "skipped": ("s", "tab:gray"), "not-found": ("x", "tab:red"),
              "reassigned": ("^", "tab:orange"), "unassigned": ("v", "tab:purple"), "failed": ("*", "black"),
              "unavailable": ("D", "tab:brown")}


def read(path: Path) -> tuple[dict[str, list[tuple[float, dict]]], list[tuple[float, dict]], dict[str, str]]:
    """(robot -> [(seconds, state)], [(seconds, task)], metadata) of a recording."""
    states: dict[str, list[tuple[float, dict]]] = defaultdict(list)
    tasks: list[tuple[float, dict]] = []
    metadata: dict[str, str] = {}
    with path.open("rb") as f:
        reader = make_reader(f)
        for record in reader.iter_metadata():
            if record.name == "coapkb":
                metadata = dict(record.metadata)
        start = None
        for _, channel, message in reader.iter_messages(log_time_order=True):
            start = message.log_time if start is None else start
            t = (message.log_time - start) / 1e9
            if channel.topic == "/robots/state":
                state = json.loads(message.data)
                states[state["robot"]].append((t, state))
            elif channel.topic == "/tasks":
                tasks.append((t, json.loads(message.data)))
    return states, tasks, metadata


def draw(path: Path, out: Path, ontologies: Path) -> None:
    states, tasks, metadata = read(path)
    layout, docks = warehouse(ontologies)
    if layout is None:
        raise SystemExit(f"no warehouse layout in {ontologies}")
    fig, (top, right) = plt.subplots(1, 2, figsize=(13, 5.2), gridspec_kw={"width_ratios": [1.1, 1]})
    for aisle in range(1, layout.aisles + 1):
        x, y0 = layout.xy(Position(aisle, 1))
        _, y1 = layout.xy(Position(aisle, layout.racks_per_aisle))
        top.add_patch(plt.Rectangle((x + layout.aisle_spacing_m / 2 - 0.4, y0 - layout.rack_length_m / 2), 0.8,
                                    y1 - y0 + layout.rack_length_m, color="#b8a07a", zorder=1))
    for dock in docks:
        top.plot(*layout.xy(dock), marker="P", color="tab:green", markersize=11, zorder=3)
    top.plot(*layout.xy(Position(1, 0)), marker="*", color="black", markersize=14, zorder=3)
    top.annotate("depot", layout.xy(Position(1, 0)), textcoords="offset points", xytext=(6, -12))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for index, (robot, seen) in enumerate(sorted(states.items())):
        colour = colours[index % len(colours)]
        points = [_xy(layout, s["aisle"], s["rack"]) for _, s in seen]
        top.plot([p[0] for p in points], [p[1] for p in points], "-o", color=colour, markersize=3, linewidth=1.2,
                 label=robot, zorder=4)
        right.step([t for t, _ in seen], [s["done"] for _, s in seen], where="post", color=colour, label=f"{robot} jobs done")
    top.set_aspect("equal")
    top.set_xlabel("x (m)")
    top.set_ylabel("y (m)")
    top.set_title("the warehouse and each robot's track")
    top.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)
    for fate, (marker, colour) in FATE_MARKS.items():
        when = [t for t, task in tasks if task["fate"] == fate]
        if when:
            right.plot(when, [-0.6] * len(when), marker, color=colour, linestyle="none", label=f"task {fate}")
    right.set_xlabel("time since the first message (s)")
    right.set_ylabel("jobs done")
    right.set_title("jobs done per robot; tasks by fate (decided, or found missing)")
    right.legend(loc="upper left", fontsize=8)
    # The whole command, over as many lines as it takes, and room kept above
    # the panels for them (tight_layout alone let a long one run off the figure).
    # Broken at spaces only: a path's hyphen is not where a line may end.
    title = textwrap.wrap(f"{path.name}: {metadata.get('command', '')}", 150, break_on_hyphens=False)
    fig.suptitle("\n".join(title), fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.035 * len(title)))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")


def _xy(layout, aisle: float, rack: float) -> tuple[float, float]:
    low = Position(max(1, min(layout.aisles, int(aisle))), max(0, min(layout.racks_per_aisle + 1, int(rack))))
    x, y = layout.xy(low)
    return x + (aisle - low.aisle) * layout.aisle_spacing_m, y + (rack - low.rack) * layout.rack_length_m


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.mcap_picture",
                                description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("mcap", type=Path)
    p.add_argument("--out", type=Path, default=Path("/tmp/run.png"))
    p.add_argument("--ontologies", type=Path, default=ROOT / "ontologies", help="the KBs the run used")
    args = p.parse_args(argv)
    draw(args.mcap, args.out, args.ontologies)
    return 0


if __name__ == "__main__":
    sys.exit(main())
