"""The ``coapkb`` command line, one module per subcommand.

Every user mistake ends in one ``coapkb: error: ...`` line and a non-zero
exit (2 for usage, 1 for a failed operation), never a traceback: any
:class:`~coapkb.errors.CoapkbError` that reaches :func:`main` is printed so.
Each subcommand imports what it runs when it runs, and :func:`main` builds
only the chosen subcommand's options (the benchmark's need its systems and
the harness), so ``coapkb agent`` loads a robot's modules only: with a
hundred robot processes starting on one machine, every import is paid a
hundred times.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
from collections.abc import Callable, Sequence

from ..errors import CoapkbError
from . import agent, bench, dump, feed, keys, query, serve, sim, team, update, world
from .common import Parser, UserError
from .render import render

__all__ = ["UserError", "build_parser", "main", "render"]


def build_parser(only: str | None = None) -> Parser:
    """The whole command line, or with ``only`` the one subcommand of that
    name (what :func:`main` runs: the others' options are not imported)."""
    parser = Parser(prog="coapkb", description="Semantic knowledge bases for robot teams over CoAP")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub: argparse._SubParsersAction[Parser] = parser.add_subparsers(
        dest="command", required=True, metavar="COMMAND")
    for name, add in COMMANDS.items():
        if only is None or name == only:
            add(sub)
    return parser


#: Each subcommand's name and the function adding its parser.
COMMANDS: dict[str, Callable[[argparse._SubParsersAction[Parser]], None]] = {
    "demo": team.add_demo, "team": team.add_team, "feed": feed.add_feed, "serve": serve.add_serve,
    "agent": agent.add_agent, "query": query.add_query, "bench": bench.add_bench, "keys": keys.add_keys,
    "sim": sim.add_sim, "update": update.add_update, "dump": dump.add_dump, "world": world.add_world,
}


def _command(argv: Sequence[str]) -> str | None:
    """The subcommand ``argv`` names, if it names a known one before any
    option other than ``-v`` (else the whole parser reports the mistake)."""
    for word in argv:
        if word in COMMANDS:
            return word
        if word not in ("-v", "-vv", "-vvv", "--verbose"):
            return None
    return None


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = _command(argv)
    parser = build_parser(only=command)
    if command is not None:
        parser.help_hint = f"coapkb {command} --help"
    args = parser.parse_args(argv)
    args.argv = argv
    level = (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        return int(asyncio.run(args.run(args)))
    except CoapkbError as exc:  # a user mistake, a bad file, an unreachable peer: one line
        parser.exit(2, f"coapkb: error: {exc}\n")
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
