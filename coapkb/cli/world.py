"""``coapkb world``: the simulated world a team of robots started by hand shares."""

from __future__ import annotations

import argparse
import asyncio
import signal
from pathlib import Path

from .common import Parser, UserError


def add_world(sub: argparse._SubParsersAction[Parser]) -> None:
    p = sub.add_parser(
        "world",
        help="serve the ground truth of the shelves to robots run by hand (world = PATH in their TOML)",
        description="Robots whose TOML says world = \"PATH\" ask this at the shelf whether the object is there.\n"
        "Every object is where the KB says, except those misplaced here and those a robot already took.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("path", help="the Unix socket to serve on (e.g. /tmp/coapkb-world.sock)")
    p.add_argument("--misplace", action="append", default=[], metavar="OBJECT",
                   help="the object is not where the KB says (repeatable)")
    p.set_defaults(run=_world)


async def _world(args: argparse.Namespace) -> int:
    from ..world.service import WorldServer
    from ..world.truth import WorldTruth

    path = Path(args.path)
    if not path.parent.is_dir():
        raise UserError(f"{path.parent} is not a directory")
    if path.exists() and not path.is_socket():
        raise UserError(f"{path} exists and is not a socket: give a new path")
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        async with WorldServer(WorldTruth.with_misplaced(args.misplace), path) as server:
            misplaced = f"; misplaced: {', '.join(args.misplace)}" if args.misplace else ""
            print(f"world serving on {path}{misplaced}", flush=True)
            await stop.wait()
            taken = server.truth.taken
            print(f"\n{len(taken)} objects taken" + ("".join(f"\n  {o}: {t}" for o, t in taken.items())))
    except OSError as exc:
        raise UserError(f"cannot serve on {path}: {exc.strerror or exc}") from None
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
    return 0
