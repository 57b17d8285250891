"""``coapkb agent``: one robot from its TOML configuration."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from .common import Parser, until_signalled


def add_agent(sub: argparse._SubParsersAction[Parser]) -> None:
    p = sub.add_parser("agent", help="run one robot from its TOML configuration")
    p.add_argument("--config", required=True, metavar="FILE", help="the robot's TOML file")
    p.add_argument("--query-wire", choices=("compact", "seed"), default="compact",
                   help="compact: named queries + CBOR; seed: full SPARQL text + JSON, like the seed paper")
    p.add_argument("--data-dir", metavar="DIR",
                   help="keep the KB's writes in DIR and restore them at the next start "
                        "(default: the TOML's data_dir; without it, in memory only)")
    p.set_defaults(run=_agent)


async def _agent(args: argparse.Namespace) -> int:
    from ..agent.robot import Robot
    from ..config import load_config

    config = load_config(args.config)
    if args.data_dir is not None:
        config = dataclasses.replace(config, data_dir=Path(args.data_dir))
    robot = await Robot.start(config, query_wire=args.query_wire)
    assert robot.server is not None  # Robot.start returns a serving robot
    # Ready once in touch with the team (or after a bound): the handshakes
    # with the teammates are then not in the first task's queries.
    heard, teammates = await robot.join_team()
    try:
        await until_signalled(f"robot {config.robot_id} ready on {robot.server.endpoint}, "
                              f"heard from {heard} of {teammates} teammates")
    finally:
        await robot.aclose()
    return 0
