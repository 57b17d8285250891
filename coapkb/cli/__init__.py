"""The ``coapkb`` command line, one module per subcommand.

Every user mistake ends in one ``coapkb: error: ...`` line and a non-zero
exit (2 for usage, 1 for a failed operation), never a traceback: any
:class:`~coapkb.errors.CoapkbError` that reaches :func:`main` is printed so.
Each subcommand imports what it runs when it runs, so ``coapkb agent``
loads a robot's modules only.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
from typing import Callable, Sequence

from ..errors import CoapkbError
from . import agent, bench, feed, keys, query, serve, team
from .common import UserError
from .render import render

__all__ = ["UserError", "build_parser", "main", "render"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="coapkb", description="Semantic knowledge bases for robot teams over CoAP")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in COMMANDS:
        add(sub)
    return parser


COMMANDS: list[Callable[[argparse._SubParsersAction], None]] = [
    team.add_demo, team.add_team, feed.add_feed, serve.add_serve, agent.add_agent, query.add_query,
    bench.add_bench, keys.add_keys,
]


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        return asyncio.run(args.run(args))
    except CoapkbError as exc:  # a user mistake, a bad file, an unreachable peer: one line
        parser.exit(2, f"coapkb: error: {exc}\n")
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
