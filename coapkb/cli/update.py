"""``coapkb update``: a SPARQL 1.1 Update to a robot's knowledge base."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from ..kb.write_concern import Ack
from ..kb.write_ids import parse_wid
from .common import Parser, UserError, add_robot_client, ask_robot
from .query import read_text, split_robot_uri

if TYPE_CHECKING:
    from ..kb.client import KBClient, WriteAnswer

#: The exit status of a write made, but reaching less than --ack asked.
SHORT_EXIT = 3


def add_update(sub: argparse._SubParsersAction[Parser]) -> None:
    p = sub.add_parser(
        "update",
        help="write to a robot's knowledge base: a SPARQL 1.1 Update",
        description="Examples:\n"
        "  coapkb update coap://127.0.0.1:5683 'PREFIX obj: <http://www.tcs.org/2018/Object#>\n"
        "      INSERT DATA { obj:Gucci_bag_14 obj:note \"checked\" }'\n"
        "  coapkb update coap://127.0.0.1:5683 @moves.ru\n"
        "  coapkb update --ack all coap://127.0.0.1:5683 @moves.ru\n"
        "  coapkb update --write-id op7.12 coap://127.0.0.1:5683 @moves.ru   # sent again: made once\n\n"
        "Prints one line: the knowledge base's new version (its ETag), then the robot's\n"
        "answer, e.g. '4f1c09a2b7d3e8a0 removed 1, added 1; ack 2 (2 of 3 holders)'.\n"
        "A write that reached less than --ack asked is still made, and spreads: it is\n"
        "said in one line on stderr and the exit status is 3 (do not send it again).",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("uri", help="robot (coap://, zmq://, zenoh://, ... HOST:PORT)")
    p.add_argument("update", help="SPARQL Update text; @FILE reads a file, - reads stdin")
    p.add_argument("--if-match", metavar="VERSION", help="write only if the KB is still at this version (hex ETag)")
    p.add_argument("--idempotent", action="store_true", help="send iPATCH (the update may be applied twice)")
    p.add_argument("--ack", choices=[a.value for a in Ack], metavar="LEVEL",
                   help="answer once the write is local (here: on disk with a data folder), on 2 holders "
                        "(the robot's default) or on all the holders it pushes to (?ack= on the request)")
    p.add_argument("--write-id", metavar="WRITER.N",
                   help="the write's id (?wid= on the request): the robot makes a write once, however often "
                        "it is sent with the same id, and answers a repeat as it answered the first; "
                        "by default a new id (a script that sends a write again passes the id it used)")
    add_robot_client(p, timeout_s=30.0)
    p.set_defaults(run=_update)


async def _update(args: argparse.Namespace) -> int:
    from ..kb.client import WriteShort

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
    if args.write_id is not None:
        try:
            parse_wid(args.write_id)
        except ValueError as exc:
            raise UserError(f"--write-id: {exc}") from None

    async def write(client: KBClient) -> WriteAnswer | WriteShort:
        try:
            return await client.write(peer, text, if_match=if_match, idempotent=args.idempotent,
                                      ack=None if args.ack is None else Ack(args.ack), write_id=args.write_id)
        except WriteShort as short:  # written, and spreading: not a failure to retry
            return short

    answer = await ask_robot(args, peer, write)
    if answer is None:
        return 1
    if isinstance(answer, WriteShort):
        print(f"coapkb: {peer} answered {answer.response.status.dotted}: {answer.response.text()}", file=sys.stderr)
        return SHORT_EXIT
    # The version is the new ETag (--if-match takes it), named so.
    print(f"version {answer.version.hex()}" + (f": {answer.text}" if answer.text.strip() else ""))
    return 0
