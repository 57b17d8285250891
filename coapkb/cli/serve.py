"""``coapkb serve``: knowledge base files served as a robot's resources."""

from __future__ import annotations

import argparse
import secrets
from pathlib import Path

from ..transport import SCHEMES
from .common import Parser, UserError, add_credentials, parse_endpoint, server_security, until_signalled


def add_serve(sub: argparse._SubParsersAction[Parser]) -> None:
    p = sub.add_parser("serve", help="serve knowledge base files as a robot's resources")
    p.add_argument("--kb", nargs="+", required=True, metavar="FILE", help="RDF files (.owl, .ttl, .nt)")
    p.add_argument("--bind", default="127.0.0.1:5683", metavar="HOST:PORT")
    p.add_argument("--transport", choices=SCHEMES, default="coap")
    p.add_argument("--backend", choices=("oxigraph", "rdflib"), default="oxigraph")
    p.add_argument("--index-dir", metavar="DIR",
                   help="keep the KB as an on-disk index in DIR: built once, opened in milliseconds later (oxigraph)")
    add_credentials(p, "central")
    p.add_argument("--writable", action="store_true",
                   help="take writes (PATCH /kb) without credentials; with --credentials, the team's access table decides")
    p.add_argument("--data-dir", metavar="DIR",
                   help="keep the writes in DIR (a journal and snapshots) and restore them at the next start; "
                        "default: in memory only")
    p.add_argument("--row-limit", type=int, default=1000)
    p.add_argument("--time-budget", type=float, default=2.0, metavar="SECONDS")
    p.set_defaults(run=_serve)


async def _serve(args: argparse.Namespace) -> int:
    from ..kb.durable import open_live
    from ..kb.limits import QueryLimits
    from ..kb.live import LiveKB, wall_ms
    from ..kb.resources import KBResources
    from ..kb.store import KnowledgeBase
    from ..transport import serve
    from ..transport.router import Router

    endpoint = parse_endpoint(args.bind, args.transport)
    try:
        limits = QueryLimits(row_limit=args.row_limit, time_budget_s=args.time_budget)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if args.index_dir is not None and args.backend != "oxigraph":
        raise UserError("--index-dir needs --backend oxigraph")
    writable = args.writable or args.credentials is not None
    if writable and (args.backend != "oxigraph" or args.index_dir is not None):
        raise UserError("a writable KB needs the in-memory oxigraph backend (no --index-dir, no --backend rdflib)")
    if args.data_dir is not None and not writable:
        raise UserError("--data-dir keeps writes: it needs --writable or --credentials")
    base = KnowledgeBase.load(args.kb, backend=args.backend, index_dir=args.index_dir)
    keeper = None
    kb: KnowledgeBase | LiveKB = base
    if writable:
        data_dir = None if args.data_dir is None else Path(args.data_dir)
        kb, keeper = open_live(base, args.identity, secrets.randbelow(2**32), data_dir, wall_ms=wall_ms)
    router = Router()
    KBResources(kb, limits, read_only="this knowledge base is read-only: start coapkb serve with --writable "
                                      "(or --credentials: the team's access table then decides who writes)").mount(router)
    server = await serve(router, endpoint, security=server_security(args))
    mode = "writable" if writable else "read-only"
    if keeper is not None:
        mode += f", kept in {keeper.path}"
    if args.credentials is not None:
        mode += f", OSCORE/EDHOC as {args.identity}, team access policy"
    try:
        await until_signalled(f"serving {', '.join(kb.names)} ({kb.triple_count} triples, {kb.backend}, {mode}) "
                              f"on {server.endpoint}")
    finally:
        await server.aclose()
        if keeper is not None:
            keeper.close()
    return 0
