"""``coapkb bench``: benchmark runs on kernel-emulated links."""

from __future__ import annotations

import argparse

from .common import Parser, UserError


def add_bench(sub: argparse._SubParsersAction[Parser]) -> None:
    from ..bench import run as bench

    p = sub.add_parser(
        "bench",
        help="benchmark systems on kernel-emulated slow, lossy links (root); one CSV row per run",
        description="Each run puts every robot, the central server and the task feeder in its own network "
        "namespace behind a tbf shaper and a loss rule (docs/link-emulation.md, docs/benchmarks.md).",
    )
    bench.add_arguments(p)
    p.set_defaults(run=_bench)


async def _bench(args: argparse.Namespace) -> int:
    from ..bench import run as bench

    try:
        return await bench.main(args)
    except ValueError as exc:
        raise UserError(str(exc)) from None
