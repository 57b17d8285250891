"""``coapkb feed``: the team's feeder for robots started by hand."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from .common import Parser, UserError
from .team import open_recorder, task_lines

if TYPE_CHECKING:
    from ..feeder.restock import Restocker
    from ..feeder.team_folder import TeamFolder


def _location_kb(team: TeamFolder) -> Path:
    """The Location KB's file, as a robot of the team loads it (the
    warehouse a recording draws)."""
    for config in team.configs.values():
        for path in config.kb_files:
            if path.name == "Location.owl":
                return Path(path)
    raise UserError(f"no robot in {team.folder} loads a Location.owl: nothing to draw the warehouse from")


async def _restocker(team: TeamFolder) -> Restocker:
    """What makes a task file's deliveries for robots run by hand: into the
    Location KB of the robots that write (as the team's operator), and into
    the world their TOML files name (``world = "PATH"``), if any."""
    from ..feeder.restock import Restocker, operator_security, shelf_places
    from ..kb.store import KnowledgeBase
    from ..transport import open_client
    from ..world.service import WorldClient

    holders = [[(r, team.configs[r].bind) for r in cluster
                if team.configs[r].kb_writable and "Location" in team.configs[r].team[r].kbs]
               for cluster in team.roster.clusters]
    worlds = {c.world for c in team.configs.values() if c.world is not None}
    expected = {e.hostport: r for r, e in team.roster.endpoints.items()}
    security = operator_security(team.settings.transport, team.credentials, expected)
    places = shelf_places(KnowledgeBase.load([_location_kb(team)]))
    client = await open_client(team.settings.transport, security=security)
    return Restocker(client, places, holders if any(holders) else [],
                     WorldClient(next(iter(worlds))) if worlds else None, timeout_s=team.settings.query_timeout_s)


def add_feed(sub: argparse._SubParsersAction[Parser]) -> None:
    p = sub.add_parser(
        "feed",
        help="feed tasks to robots started by hand (coapkb agent --config DIR/RobotN.toml), as the team's feeder",
        description="Reads the robots' TOML files in --team (their endpoints, clusters and key directory), "
        "checks that every robot answers, posts the tasks in order and prints what each robot decided. "
        "Example: examples/three-robots/README.md",
    )
    p.add_argument("--team", required=True, metavar="DIR", help="the folder holding the robots' TOML files")
    p.add_argument("--tasks-file", required=True, metavar="FILE", help="one object name per line")
    p.add_argument("--timeout", type=float, default=120.0, metavar="SECONDS",
                   help="how long one task's decisions may take (default 120)")
    p.add_argument("--answer-timeout", type=float, default=10.0, metavar="SECONDS",
                   help="how long each robot has to answer before feeding starts (default 10)")
    p.add_argument("--costs", action="store_true", help="also print every robot's cost for each task")
    p.add_argument("--record", metavar="OUT.mcap", help="record the run as an MCAP file Foxglove opens")
    p.add_argument("--foxglove", metavar="[HOST:]PORT",
                   help="serve the run live to Foxglove (WebSocket protocol); host 127.0.0.1 by default")
    p.set_defaults(run=_feed)


async def _feed(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from ..agent.observed_states import STATE_PATH
    from ..feeder import FateCounts, Feeder, TaskRecord, read_tasks_file
    from ..feeder.tasks import Restock, task_count
    from ..feeder.team_folder import read_team_folder

    if not args.timeout > 0 or not args.answer_timeout > 0:
        raise UserError("--timeout and --answer-timeout must be positive")
    team = read_team_folder(args.team, task_timeout_s=args.timeout)
    tasks = read_tasks_file(args.tasks_file)
    if not tasks:
        raise UserError(f"no tasks in {args.tasks_file}")
    if args.record and not args.record.endswith(".mcap"):
        raise UserError("--record writes an MCAP file: give it a name ending in .mcap")
    security = team.security()
    recorder = open_recorder(args, list(team.roster.endpoints), _location_kb(team), team=str(team.folder))
    print(f"feeding {task_count(tasks)} task(s) to {', '.join(f'{r} {e}' for r, e in team.roster.endpoints.items())}"
          + ("" if security is None else f" (keys: {team.credentials})"), flush=True)

    def decided(record: TaskRecord) -> None:
        print(task_lines(record, args.costs), flush=True)
        if recorder is not None:
            recorder.task(record)

    restocker = await _restocker(team) if any(isinstance(t, Restock) for t in tasks) else None
    try:
        # A recording shows where each robot is: its whole state, not only its outcome.
        settings = team.settings if recorder is None else replace(team.settings, watch=STATE_PATH)
        async with Feeder.open(team.roster, settings, security) as feeder:
            await feeder.check_ready(args.answer_timeout,
                                     {r: f"is it running? start it with: {team.start_command(r)}" for r in team.files})
            if recorder is not None:
                feeder.watcher.listeners.append(recorder.robot_state)
            feeder.restocker = restocker
            outcome = await feeder.feed(tasks, decided)
        if recorder is not None:
            recorder.final_fates(outcome.tasks)
    finally:
        if recorder is not None:
            recorder.close()
        if restocker is not None:
            await restocker.client.aclose()
            close = getattr(restocker.world, "aclose", None)  # a WorldClient's connection
            if close is not None:
                await close()
    disputed = [t for t in outcome.tasks if not t.agreed]
    print(f"{FateCounts.of(outcome.tasks).line()}; "
          f"coordination {outcome.coordination_s:.2f} s, completion {outcome.completion_s:.2f} s"
          + (f"; restocked {restocker.done}" if restocker is not None else ""))
    return 1 if disputed else 0
