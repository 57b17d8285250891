"""``coapkb query``: SPARQL or a named query to a robot, printed."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from urllib.parse import parse_qsl, urlsplit

from ..transport.base import ClientTransport, Endpoint
from ..transport.messages import ContentFormat, Method, Request
from .common import Parser, UserError, add_robot_client, ask_robot, client_security, parse_endpoint
from .render import render

FORMAT_ACCEPT = {"cbor": ContentFormat.CBOR, "json": ContentFormat.JSON}


def add_query(sub: argparse._SubParsersAction[Parser]) -> None:
    p = sub.add_parser(
        "query",
        help="query a robot: SPARQL text, or a named query URI",
        description="Examples:\n"
        "  coapkb query coap://127.0.0.1:5683 'SELECT * WHERE { ?s ?p ?o } LIMIT 3'\n"
        "  coapkb query 'coap://127.0.0.1:5683/kb/q/object-exists?name=Gucci_bag_14'",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("uri", help="robot (coap://, zmq://, zenoh://, zenoh+udp:// or zenoh+quic://HOST:PORT), or a /kb/q/NAME?param=value URI")
    p.add_argument("sparql", nargs="?", help="query text; @FILE reads a file, - reads stdin")
    p.add_argument("--accept", choices=tuple(FORMAT_ACCEPT), default="cbor", help="answer format on the wire")
    p.add_argument("--format", choices=("table", "json", "csv"), default="table", help="output format")
    p.add_argument("--method", choices=("fetch", "post", "get"), default="fetch")
    p.add_argument("--observe", action="store_true",
                   help="keep printing the answer each time it changes (RFC 7641; SPARQL text is observed by FETCH)")
    add_robot_client(p, timeout_s=30.0)
    p.set_defaults(run=_query)


def read_text(arg: str | None, what: str = "query") -> str | None:
    """``arg`` itself, or a file's text (``@FILE``), or stdin's (``-``)."""
    if arg is None:
        return None
    if arg == "-":
        return sys.stdin.read()
    if arg.startswith("@"):
        try:
            return Path(arg[1:]).read_text(encoding="utf-8")
        except OSError as exc:
            raise UserError(f"cannot read {what} file {arg[1:]}: {exc.strerror}") from None
    return arg


def split_robot_uri(uri: str) -> tuple[Endpoint, str]:
    """A robot's endpoint and the path of ``uri`` (``coap://`` if no scheme)."""
    parts = urlsplit(uri if "://" in uri else f"coap://{uri}")
    return parse_endpoint(f"{parts.scheme}://{parts.netloc}", parts.scheme), parts.path


async def _query(args: argparse.Namespace) -> int:
    from ..model.results import AskResult, GraphResult
    from ..transport import open_client

    parts = urlsplit(args.uri if "://" in args.uri else f"coap://{args.uri}")
    peer, _ = split_robot_uri(args.uri)
    text = read_text(args.sparql)
    named = parts.path.startswith("/kb/q/")
    if named and text:
        raise UserError("give either a named query URI or SPARQL text, not both")
    if not named and not text:
        raise UserError("no query: give SPARQL text (or @FILE, or -) or a /kb/q/NAME URI")
    if parts.path not in ("", "/") and not named:
        raise UserError(f"unexpected path {parts.path!r}: use the robot's base URI or /kb/q/NAME")
    accept = FORMAT_ACCEPT[args.accept]
    if args.observe:
        from ..kb.client import named_request, sparql_request

        if named:
            request = named_request(parts.path.rsplit("/", 1)[1], dict(parse_qsl(parts.query)), accept=accept)
        else:
            request = sparql_request(text or "", accept=accept, method=Method.FETCH)
        transport = await open_client(peer.scheme, security=client_security(args, peer))
        try:
            return await _observe(transport, peer, request, args)
        finally:
            await transport.aclose()
    if named:
        name, params = parts.path.rsplit("/", 1)[1], dict(parse_qsl(parts.query))
        result = await ask_robot(args, peer, lambda client: client.named(peer, name, params, accept=accept))
    else:
        method = Method(args.method.upper())
        result = await ask_robot(args, peer, lambda client: client.sparql(peer, text or "", accept=accept,
                                                                           method=method))
    if result is None:
        return 1
    sys.stdout.write(render(result, args.format))
    if args.format == "csv" and not isinstance(result, AskResult) and result.truncated:
        # The table's footer and SPARQL-JSON's "truncated" say so; CSV has no room for it.
        shown = len(result.triples if isinstance(result, GraphResult) else result.rows)
        print(f"coapkb: {peer} truncated the answer at its row limit: the CSV holds its first {shown} rows",
              file=sys.stderr)
    return 0


async def _observe(transport: ClientTransport, peer: Endpoint, request: Request, args: argparse.Namespace) -> int:
    """Print the answer, then again at every change, until interrupted or
    the robot answers an error.  A re-registration (no notification within
    Max-Age: the robot restarted, or lost the observation) and the loss of
    the robot (it is tried again until it answers) are one line each on
    stderr; the answer follows as usual when it changed meanwhile."""
    from ..kb.client import KBClient, QueryFailed
    from ..transport import TransportError
    from ..transport.observation import Notice

    def notice(what: Notice) -> None:
        print(f"coapkb: {what}", file=sys.stderr, flush=True)

    count = 0
    try:
        async for result in KBClient(transport).observe(peer, request, on_notice=notice):
            if count:
                print(f"-- changed (notification {count})", flush=True)
            sys.stdout.write(render(result, args.format))
            sys.stdout.flush()
            count += 1
    except QueryFailed as exc:
        print(f"coapkb: {peer} answered {exc}", file=sys.stderr)
        return 1
    except TransportError as exc:
        print(f"coapkb: {exc}", file=sys.stderr)
        return 1
    print(f"coapkb: {peer} ended the observation", file=sys.stderr)
    return 0
