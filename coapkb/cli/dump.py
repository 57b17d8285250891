"""``coapkb dump``: every triple a robot's knowledge base holds (or one
module's), as N-Triples: a backup, or two replicas compared with ``diff``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from .common import Parser, UserError, add_robot_client, ask_robot, require_folder_of
from .query import split_robot_uri

if TYPE_CHECKING:
    from ..kb.client import KBClient
    from ..transport.messages import Response

MODULES = ("Object", "Location", "Capability")


def add_dump(sub: argparse._SubParsersAction[Parser]) -> None:
    p = sub.add_parser(
        "dump",
        help="write a robot's whole knowledge base (or one module) as N-Triples",
        description="Examples:\n"
        "  coapkb dump coap://127.0.0.1:5683 --module Object > object.nt\n"
        "  coapkb dump coap://127.0.0.1:5683 --out robot1.nt\n\n"
        "GET /kb/dump: every triple the robot's queries see (with --module, those whose\n"
        "subject is in the module's namespace or is its ontology), one line each,\n"
        "sorted, so two replicas' dumps compare with diff. No row limit: a long answer\n"
        "comes block-wise. One line on stderr says how many triples and the knowledge\n"
        "base's version.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("uri", help="robot (coap://, zmq://, zenoh://, ... HOST:PORT)")
    p.add_argument("--module", choices=MODULES, help="one module's triples only")
    p.add_argument("--out", type=Path, metavar="FILE", help="write the triples here (default: standard output)")
    add_robot_client(p, timeout_s=120.0)
    p.set_defaults(run=_dump)


async def _dump(args: argparse.Namespace) -> int:
    from ..transport.messages import ContentFormat, Method, Request

    peer, path = split_robot_uri(args.uri)
    if path not in ("", "/", "/kb", "/kb/dump"):
        raise UserError(f"unexpected path {path!r}: give the robot's base URI")
    if args.out is not None:
        require_folder_of(args.out, "--out")
    request = Request(Method.GET, "/kb/dump", query={"module": args.module} if args.module else {},
                      accept=ContentFormat.TEXT)

    async def fetch(client: KBClient) -> Response:
        return await client.call(peer, request, args.timeout)

    response = await ask_robot(args, peer, fetch)
    if response is None:
        return 1
    if args.out is None:
        sys.stdout.buffer.write(response.payload)
        sys.stdout.flush()
    else:
        args.out.write_bytes(response.payload)
    triples = response.payload.count(b"\n")
    version = "" if response.etag is None else f", version {response.etag.hex()}"
    print(f"{triples} triples, {len(response.payload)} bytes{version}", file=sys.stderr)
    return 0
