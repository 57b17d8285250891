"""A robot's memory: VmRSS of real robot processes on CoAP (OSCORE, as by default).

Usage::

    .venv/bin/python -m experiments.robot_rss [--robots 3] [--tasks 10] [--replication 1 2]
        [--out experiments/results/robot_rss.csv]

First the import-only cost, each in a fresh interpreter: ``import
coapkb.agent.robot`` alone, then everything a CoAP robot process imports
(the command line, the robot, the CoAP transport and its OSCORE/EDHOC
security).  Then, for each ``--replication`` (robots of a cluster holding
each KB module: 1 = one module per robot, 2 = two), a team of ``--robots``
robots on loopback (each a ``python -m coapkb agent`` process):
VmRSS and PSS (``/proc/PID/smaps_rollup``: shared library pages divided
among the processes mapping them) of each robot once all are up, and again
after ``--tasks`` tasks.  Prints a table and writes one CSV row per figure.
"""

from __future__ import annotations

import argparse
import asyncio
import csv
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from coapkb.harness.team import Team, TeamSpec, cluster_modules, draw_tasks

RESULTS = Path(__file__).resolve().parent / "results"

#: What a fresh interpreter imports for each import-only row.
IMPORTS = {
    "import coapkb.agent.robot": "import coapkb.agent.robot",
    "a CoAP robot's imports": (
        "import coapkb.cli as cli; cli.build_parser(only='agent'); "
        "import coapkb.agent.robot, coapkb.transport.coap, coapkb.security.coap"
    ),
}


@dataclass(frozen=True)
class Figure:
    """One measured process at one moment."""

    what: str
    replication: int | None
    robot: str
    modules: str
    rss_mib: float
    pss_mib: float | None


def _kib(text: str, field: str) -> int:
    for line in text.splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"no {field}")


def memory_mib(pid: int | str) -> tuple[float, float]:
    """(VmRSS, PSS) of a process, MiB."""
    rss = _kib(Path(f"/proc/{pid}/status").read_text(), "VmRSS")
    pss = _kib(Path(f"/proc/{pid}/smaps_rollup").read_text(), "Pss")
    return rss / 1024, pss / 1024


def import_only(label: str, code: str) -> Figure:
    probe = f"{code}\nfrom pathlib import Path\nprint(Path('/proc/self/status').read_text())"
    out = subprocess.run([sys.executable, "-c", probe], check=True, capture_output=True, text=True).stdout
    return Figure(f"import: {label}", None, "-", "-", _kib(out, "VmRSS") / 1024, None)


async def team_figures(robots: int, tasks: list[str], replication: int) -> list[Figure]:
    spec = TeamSpec(robots=robots, transport="coap", replication=replication)
    modules = {r: "+".join(cluster_modules(i, spec)) for i, r in enumerate(spec.robot_ids)}
    figures = []
    async with Team.launch(spec) as team:
        for robot, proc in team.processes.items():
            figures.append(Figure("robot, idle", replication, robot, modules[robot], *memory_mib(proc.pid)))
        await team.run(tasks)
        for robot, proc in team.processes.items():
            figures.append(Figure(f"robot, after {len(tasks)} tasks", replication, robot, modules[robot],
                                  *memory_mib(proc.pid)))
    return figures


async def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.robot_rss", description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, default=3)
    parser.add_argument("--tasks", type=int, default=10)
    parser.add_argument("--replication", type=int, nargs="+", default=[1, 2],
                        help="robots of a cluster holding each KB module (one team per value)")
    parser.add_argument("--out", type=Path, default=RESULTS / "robot_rss.csv")
    args = parser.parse_args()
    figures = [import_only(label, code) for label, code in IMPORTS.items()]
    tasks = draw_tasks(args.tasks)
    for replication in args.replication:
        figures += await team_figures(args.robots, tasks, replication)
    print("| what | replication | robot | KB modules | VmRSS (MiB) | PSS (MiB) |")
    print("|---|---|---|---|---|---|")
    for f in figures:
        pss = "" if f.pss_mib is None else f"{f.pss_mib:.1f}"
        print(f"| {f.what} | {f.replication or ''} | {f.robot} | {f.modules} | {f.rss_mib:.1f} | {pss} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with args.out.open("w", newline="") as out:
        writer = csv.writer(out)
        writer.writerow(["what", "replication", "robot", "modules", "rss_mib", "pss_mib"])
        for f in figures:
            writer.writerow([f.what, f.replication or "", f.robot, f.modules, f"{f.rss_mib:.1f}",
                             "" if f.pss_mib is None else f"{f.pss_mib:.1f}"])
    print(f"wrote {args.out}")


if __name__ == "__main__":
    asyncio.run(main())
