"""``coapkb update``: a SPARQL 1.1 Update to a robot's knowledge base."""

from __future__ import annotations

import argparse

from .common import UserError, add_credentials, ask_robot
from .query import read_text, split_robot_uri


def add_update(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "update",
        help="write to a robot's knowledge base: a SPARQL 1.1 Update",
        description="Examples:\n"
        "  coapkb update coap://127.0.0.1:5683 'PREFIX obj: <http://www.tcs.org/2018/Object#>\n"
        "      INSERT DATA { obj:Gucci_bag_14 obj:note \"checked\" }'\n"
        "  coapkb update coap://127.0.0.1:5683 @moves.ru\n\n"
        "Prints the knowledge base's new version (its ETag).",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("uri", help="robot (coap://, zmq://, zenoh://, ... HOST:PORT)")
    p.add_argument("update", help="SPARQL Update text; @FILE reads a file, - reads stdin")
    p.add_argument("--if-match", metavar="VERSION", help="write only if the KB is still at this version (hex ETag)")
    p.add_argument("--idempotent", action="store_true", help="send iPATCH (the update may be applied twice)")
    p.add_argument("--timeout", type=float, default=30.0, metavar="SECONDS", help="give up after this long")
    add_credentials(p, "operator")
    p.add_argument("--peer", metavar="NAME", help="the team member serving at URI (needed over zmq; checked over coap)")
    p.set_defaults(run=_update)


async def _update(args: argparse.Namespace) -> int:
    peer, path = split_robot_uri(args.uri)
    if path not in ("", "/", "/kb"):
        raise UserError(f"unexpected path {path!r}: give the robot's base URI (or /kb)")
    text = read_text(args.update, "update")
    if not text or not text.strip():
        raise UserError("empty update")
    if_match = None
    if args.if_match is not None:
        try:
            if_match = bytes.fromhex(args.if_match)
        except ValueError:
            raise UserError(f"--if-match: expected a hex version, got {args.if_match!r}") from None
        if not 1 <= len(if_match) <= 8:
            raise UserError("--if-match: a version is 1 to 8 bytes")
    version = await ask_robot(
        args, peer, lambda client: client.update(peer, text, if_match=if_match, idempotent=args.idempotent)
    )
    if version is None:
        return 1
    print(version.hex())
    return 0



