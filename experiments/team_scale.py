"""Team size on loopback: start-up, bytes per task and robot memory, 9 against 99 robots.

Usage::

    .venv/bin/python -m experiments.team_scale [--sizes 9 99] [--tasks 200 | --tasks-per-cluster N] [--reps 1]
        [--out experiments/results/team_scale.csv]

Each size runs the same task list (``--tasks`` objects drawn with seed
``1 + rep``; with ``--tasks-per-cluster N``, N per cluster of three,
drawn alike) on a CoAP team with OSCORE keyed by EDHOC and the team's access
policy, as ``coapkb team`` runs it by default; a team larger than the
shipped KBs know runs on KBs generated for it beforehand (the generation is
timed apart: it is not part of a team's start).  Every robot is a ``python -m
coapkb agent`` process on 127.0.0.1.

What a row measures:

``processes_up_s``
    From the first robot process started until the last printed its ready
    line (a few start at a time: ``coapkb.harness.team``).
``team_up_s``
    ``processes_up_s`` plus the feeder's first round: it asks every robot
    for its state over OSCORE (an EDHOC handshake with each) and checks each
    answered.  The team can be fed from then on.  The robots' handshakes with
    their teammates happen on their first observation and are counted in the
    bytes below.
``bytes_per_task``
    Everything the robots' and the feeder's transports sent (datagram
    payloads, EDHOC and retransmissions included) from the first task fed
    until the last was executed, divided by the tasks.
``rss_*_mib``
    Robots' VmRSS once up and after the last task (median and maximum).
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from coapkb.feeder import FateCounts, Feeder
from coapkb.harness.kbs import kbs_for_team
from coapkb.harness.team import DEFAULT_ONTOLOGIES, Team, TeamSpec, draw_tasks
from coapkb.transport.base import TrafficCounters
from experiments.common import rss_mib, write_csv

ROOT = Path(__file__).resolve().parent.parent

RESULTS = ROOT / "experiments" / "results"


@dataclass(frozen=True)
class ScaleRow:
    robots: int
    tasks: int
    rep: int
    kb_generation_s: float
    processes_up_s: float
    team_up_s: float
    completion_s: float
    assigned: int
    skipped: int
    other_fates: int
    bytes_per_task: float
    messages_per_task: float
    #: Datagrams sent again, per task: the servers' CON messages
    #: (notifications: answers ride on ACKs) and the clients' copies of a
    #: request (retries and hedges, each a new NON exchange).
    retransmissions_per_task: float
    #: Notifications the robots sent (first transmissions), per task.
    notifications_per_task: float
    #: Of them, CON notifications sent again: the robots' servers'
    #: retransmissions over their notifications.
    notification_retransmission_share: float
    robot_bytes_median: float
    robot_bytes_max: float
    rss_idle_median_mib: float
    rss_idle_max_mib: float
    rss_after_median_mib: float
    rss_after_max_mib: float




async def one_team(robots: int, tasks: list[str], rep: int, workdir: Path) -> ScaleRow:
    started = time.monotonic()
    kbs = kbs_for_team(DEFAULT_ONTOLOGIES, [f"Robot{i}" for i in range(1, robots + 1)], workdir / f"kbs{robots}")
    generation_s = time.monotonic() - started
    spec = TeamSpec(robots=robots, ontologies=kbs.ontologies, time_scale=200.0)
    started = time.monotonic()
    async with Team.launch(spec) as team:
        processes_up_s = time.monotonic() - started
        async with Feeder.open(team.roster(), team.feeder_settings(), team.feeder_security()) as feeder:
            await feeder.check_ready(timeout=60)
        team_up_s = time.monotonic() - started
        idle = [rss_mib(p.pid) for p in team.processes.values()]
        record = await team.run(tasks)
        after = [rss_mib(p.pid) for p in team.processes.values()]
    per_robot = [s.traffic.bytes_sent for s in record.robot_stats.values()]
    traffic = sum((s.traffic for s in record.robot_stats.values()), TrafficCounters()) + record.feeder_traffic
    servers = sum((s.server or TrafficCounters() for s in record.robot_stats.values()), TrafficCounters())
    fates = FateCounts.of(record.tasks)
    return ScaleRow(
        robots=robots, tasks=len(tasks), rep=rep,
        kb_generation_s=round(generation_s, 2), processes_up_s=round(processes_up_s, 2),
        team_up_s=round(team_up_s, 2), completion_s=round(record.completion_s, 2),
        assigned=fates.assigned, skipped=fates.skipped, other_fates=fates.tasks - fates.assigned - fates.skipped,
        bytes_per_task=round(traffic.bytes_sent / len(tasks)),
        messages_per_task=round(traffic.messages_sent / len(tasks), 1),
        retransmissions_per_task=round(traffic.retransmissions / len(tasks), 2),
        notifications_per_task=round(servers.notifications_sent / len(tasks), 1),
        notification_retransmission_share=round(servers.retransmissions / max(1, servers.notifications_sent), 4),
        robot_bytes_median=statistics.median(per_robot), robot_bytes_max=max(per_robot),
        rss_idle_median_mib=round(statistics.median(idle), 1), rss_idle_max_mib=round(max(idle), 1),
        rss_after_median_mib=round(statistics.median(after), 1), rss_after_max_mib=round(max(after), 1),
    )


async def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m experiments.team_scale", description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[9, 99], help="team sizes, multiples of 3")
    tasks = parser.add_mutually_exclusive_group()
    tasks.add_argument("--tasks", type=int, default=200, help="tasks of every size's run")
    tasks.add_argument("--tasks-per-cluster", type=int, metavar="N",
                       help="N tasks per cluster of three instead: each size's run as busy per cluster")
    parser.add_argument("--reps", type=int, default=1)
    parser.add_argument("--out", type=Path, default=RESULTS / "team_scale.csv")
    args = parser.parse_args()
    rows: list[ScaleRow] = []
    with tempfile.TemporaryDirectory(prefix="coapkb-scale-") as tmp:
        for rep in range(args.reps):
            for robots in args.sizes:
                count = args.tasks if args.tasks_per_cluster is None else args.tasks_per_cluster * robots // 3
                row = await one_team(robots, draw_tasks(count, seed=1 + rep), rep, Path(tmp))
                print(" ".join(f"{k}={v}" for k, v in asdict(row).items()), flush=True)
                rows.append(row)
    write_csv(args.out, [f.name for f in fields(ScaleRow)], (asdict(r) for r in rows))
    print()
    print("| robots | tasks | team up (s) | completion (s) | assigned+skipped | B/task | retransmissions/task "
          "| notifications/task | of them sent again | robot RSS idle/after, median (max) MiB |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r.robots} | {r.tasks} | {r.team_up_s:.1f} | {r.completion_s:.1f} | {r.assigned + r.skipped} "
              f"| {r.bytes_per_task:,.0f} | {r.retransmissions_per_task:.2f} "
              f"| {r.notifications_per_task:.1f} | {r.notification_retransmission_share:.2%} "
              f"| {r.rss_idle_median_mib:.0f}/{r.rss_after_median_mib:.0f} "
              f"({r.rss_idle_max_mib:.0f}/{r.rss_after_max_mib:.0f}) |")
    base = {r.rep: r for r in rows if r.robots == min(args.sizes)}
    for r in rows:
        if r.robots != min(args.sizes):
            print(f"bytes per task, {r.robots} / {base[r.rep].robots} robots (rep {r.rep}): "
                  f"{r.bytes_per_task / base[r.rep].bytes_per_task:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
