"""The ``coapkb`` command line.

Every user mistake ends in one ``coapkb: error: ...`` line and a non-zero
exit (2 for usage, 1 for a failed operation), never a traceback: any
:class:`~coapkb.errors.CoapkbError` that reaches :func:`main` is printed so.
"""

from __future__ import annotations

import argparse
import asyncio
import csv
import io
import json
import logging
import signal
import sys
from pathlib import Path
from typing import Callable, Sequence
from urllib.parse import parse_qsl, urlsplit

from .errors import CoapkbError
from .wire import codec
from .transport import SCHEMES, ClientSecurity, Endpoint, ServerSecurity
from .transport.messages import ContentFormat, Method
from .world import CAPABILITY_NS, LOCATION_NS, OBJECT_NS


class UserError(CoapkbError):
    """A mistake the user can fix; printed as one line."""


# --------------------------------------------------------------------------- serve


def _add_serve(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="serve knowledge base files as a robot's resources")
    p.add_argument("--kb", nargs="+", required=True, metavar="FILE", help="RDF files (.owl, .ttl, .nt)")
    p.add_argument("--bind", default="127.0.0.1:5683", metavar="HOST:PORT")
    p.add_argument("--transport", choices=SCHEMES, default="coap")
    p.add_argument("--backend", choices=("oxigraph", "rdflib"), default="oxigraph")
    p.add_argument("--index-dir", metavar="DIR",
                   help="keep the KB as an on-disk index in DIR: built once, opened in milliseconds later (oxigraph)")
    _add_credentials(p, "central")
    p.add_argument("--row-limit", type=int, default=1000)
    p.add_argument("--time-budget", type=float, default=2.0, metavar="SECONDS")
    p.set_defaults(run=_serve)


async def _serve(args: argparse.Namespace) -> int:
    from .kb.resources import KBResources, QueryLimits
    from .kb.store import KnowledgeBase
    from .transport.router import Router
    from .transport import serve

    endpoint = _endpoint(args.bind, args.transport)
    try:
        limits = QueryLimits(row_limit=args.row_limit, time_budget_s=args.time_budget)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if args.index_dir is not None and args.backend != "oxigraph":
        raise UserError("--index-dir needs --backend oxigraph")
    kb = KnowledgeBase.load(args.kb, backend=args.backend, index_dir=args.index_dir)
    router = Router()
    KBResources(kb, limits).mount(router)
    server = await serve(router, endpoint, security=_server_security(args))
    print(f"serving {', '.join(kb.names)} ({kb.triple_count} triples, {kb.backend}) on {server.endpoint}", flush=True)
    try:
        await _until_signalled()
    finally:
        await server.aclose()
    return 0


async def _until_signalled() -> None:
    """Wait for SIGINT or SIGTERM, so a server shuts down cleanly either way."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        await stop.wait()
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)


def _endpoint(hostport: str, scheme: str) -> Endpoint:
    try:
        return Endpoint.parse(hostport, default_scheme=scheme)
    except ValueError as exc:
        raise UserError(str(exc)) from None


# --------------------------------------------------------------------------- agent


def _add_credentials(p: argparse.ArgumentParser, identity: str) -> None:
    p.add_argument("--credentials", metavar="DIR",
                   help="team key directory (coapkb keys): OSCORE keyed by EDHOC with the team's members")
    p.add_argument("--identity", default=identity, metavar="NAME",
                   help=f"whose key in --credentials to use (default {identity})")


def _client_security(args: argparse.Namespace, peer: Endpoint) -> ClientSecurity | None:
    if getattr(args, "credentials", None) is None:
        return None
    from .security import load_identity, mechanism_for

    mechanism = mechanism_for(peer.scheme)
    if mechanism.needs_server_name and not args.peer:
        raise UserError(f"--credentials over {peer.scheme}: name the member serving there with --peer "
                        f"({mechanism.title} needs its key)")
    # Otherwise the handshake finds who serves there; --peer also insists on who it is.
    return mechanism.client(load_identity(args.credentials, args.identity),
                            {peer.hostport: args.peer} if args.peer else None)


def _server_security(args: argparse.Namespace) -> ServerSecurity | None:
    if args.credentials is None:
        return None
    from .security import load_identity, server_security

    # A KB server takes queries from every member; tasks and decisions are robots' business.
    return server_security(args.transport, load_identity(args.credentials, args.identity))


def _add_keys(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("keys", help="make a team's key material: EDHOC credentials, CurveZMQ keys, TLS certificates, trust list")
    p.add_argument("--team-dir", required=True, metavar="DIR", help="a new directory (never overwritten)")
    p.add_argument("--robots", type=int, default=3, help="Robot1..RobotN")
    p.add_argument("--member", action="append", default=[], metavar="NAME:ROLE",
                   help="another member (role robot, feeder, server or client); repeatable")
    p.add_argument("--aiocoap-client", nargs=3, metavar=("IDENTITY", "PEER", "URI"),
                   help="instead: print an aiocoap-client --credentials file (.diag) for IDENTITY to talk to "
                        "member PEER at URI, from the existing --team-dir")
    p.set_defaults(run=_keys)


async def _keys(args: argparse.Namespace) -> int:
    from .security import generate_team
    from .security.keys import ROLES, aiocoap_client_credentials, default_members

    if args.aiocoap_client:
        sys.stdout.write(aiocoap_client_credentials(args.team_dir, *args.aiocoap_client))
        return 0
    if args.robots < 0:
        raise UserError("--robots must not be negative")
    members = default_members(args.robots)
    for text in args.member:
        name, sep, role = text.partition(":")
        if not sep or role not in ROLES:
            raise UserError(f"--member {text!r}: expected NAME:ROLE with ROLE one of {', '.join(ROLES)}")
        members.append((name, role))
    trust = generate_team(args.team_dir, members)
    # Names and roles only: the keys stay in their 0600 files.
    print(f"team of {len(trust.members)} in {args.team_dir}: "
          + ", ".join(f"{m.name} ({m.role})" for m in trust.members))
    print(f"give each member its {args.team_dir}/NAME.key, NAME.curve, NAME.tls.key, NAME.tls.pem, team.json and team-ca.pem; "
          "a robot's TOML names the directory: [security] credentials = \"DIR\"")
    return 0


def _add_agent(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("agent", help="run one robot from its TOML configuration")
    p.add_argument("--config", required=True, metavar="FILE", help="the robot's TOML file")
    p.add_argument("--query-wire", choices=("compact", "seed"), default="compact",
                   help="compact: named queries + CBOR; seed: full SPARQL text + JSON, like the seed paper")
    p.set_defaults(run=_agent)


async def _agent(args: argparse.Namespace) -> int:
    from .agent.robot import Robot
    from .config import load_config

    config = load_config(args.config)
    robot = await Robot.start(config, query_wire=args.query_wire)
    print(f"robot {config.robot_id} ready on {robot.server.endpoint}", flush=True)
    try:
        await _until_signalled()
    finally:
        await robot.aclose()
    return 0


# --------------------------------------------------------------------------- team

#: The seed's example task (Fig. 4), a few more picks, and one object that
#: does not exist, which every robot must skip.
DEMO_TASKS = ("Gucci_bag_14", "Nonexistent_widget_1")


def _add_team(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("team", help="run a whole team locally: robots as processes, tasks fed in order")
    p.add_argument("--robots", type=int, default=3, help="team size, a multiple of 3 (clusters of three)")
    tasks = p.add_mutually_exclusive_group(required=True)
    tasks.add_argument("--tasks", type=int, metavar="N", help="draw N objects from the Object KB")
    tasks.add_argument("--tasks-file", metavar="FILE", help="one object name per line")
    p.add_argument("--seed", type=int, default=1, help="seed for --tasks")
    p.add_argument("--mode", choices=("distributed", "central"), default="distributed")
    p.add_argument("--transport", choices=SCHEMES, default="coap")
    p.add_argument("--strategy", choices=("compute-by-all", "compute-and-communicate"), default="compute-by-all")
    p.add_argument("--query-wire", choices=("compact", "seed"), default="compact")
    p.add_argument("--ontologies", default=None, metavar="DIR", help="directory with the three .owl files")
    p.add_argument("--time-scale", type=float, default=50.0, help="simulated seconds per wall-clock second")
    p.add_argument("--replication", type=int, default=2, metavar="R",
                   help="robots of a cluster holding each KB module (1-3, default 2: one may fail)")
    p.add_argument("--kill", action="append", default=[], metavar="ROBOT@S",
                   help="SIGKILL a robot S seconds after the first task is fed, e.g. Robot4@12s (repeatable)")
    p.add_argument("--restart", action="append", default=[], metavar="ROBOT@S",
                   help="start a killed robot again at S seconds; it joins the team at the next task (repeatable)")
    p.add_argument("--stop", action="append", default=[], metavar="ROBOT@S",
                   help="SIGSTOP a robot at S seconds: cut off with its state intact (repeatable)")
    p.add_argument("--resume", action="append", default=[], metavar="ROBOT@S",
                   help="SIGCONT a stopped robot at S seconds; it finds itself fenced off and picks nothing "
                        "the others took over (repeatable)")
    p.add_argument("--discovery", choices=("static", "rd"), default="static",
                   help="how robots find their teammates: static (each config lists its cluster, default) or rd "
                        "(each config lists the robot alone; it registers in a Resource Directory the feeder "
                        "hosts and looks its cluster up there; coap only)")
    p.add_argument("--record", metavar="OUT.json", help="write the run's record here")
    p.add_argument("--insecure", action="store_true",
                   help="no OSCORE/EDHOC (coap) or CurveZMQ (zmq) and no access policy (default: on, throwaway team keys)")
    p.add_argument("--credentials", metavar="DIR", help="use this team key directory (coapkb keys) instead of throwaway keys")
    p.add_argument("--quiet", action="store_true", help="no per-task progress lines")
    p.set_defaults(run=_team)


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="the main job: 3 robots on loopback do the seed's example tasks")
    p.add_argument("--transport", choices=SCHEMES, default="coap")
    p.add_argument("--insecure", action="store_true", help="no OSCORE/EDHOC (default: on, throwaway keys)")
    p.add_argument("--record", metavar="OUT.json", help="write the run's record here")
    p.set_defaults(run=_demo)


async def _demo(args: argparse.Namespace) -> int:
    from .harness.team import draw_tasks, DEFAULT_ONTOLOGIES

    tasks = list(DEMO_TASKS[:1]) + draw_tasks(4, DEFAULT_ONTOLOGIES, seed=7, exclude=DEMO_TASKS) + list(DEMO_TASKS[1:])
    print("Demo: a team of 3 robots, each KB module on two of them "
          "(Robot1: Location+Object, Robot2: Object+Capability, Robot3: Capability+Location)")
    print("on loopback, each a separate process, over " + args.transport + "; tasks: " + ", ".join(tasks))
    print("Each robot runs the seed's four queries per task and computes every robot's cost (Wh);")
    print("the cheapest capable robot gets the task; all robots must agree.\n")
    team_args = argparse.Namespace(
        robots=3, tasks=None, tasks_file=None, seed=1, mode="distributed", transport=args.transport,
        strategy="compute-by-all", query_wire="compact", ontologies=None,
        time_scale=50.0, record=args.record, quiet=False, task_list=tasks, verbose_costs=True,
        insecure=args.insecure,
    )
    return await _team(team_args)


async def _team(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from .feeder import FeederError, TaskRecord, read_tasks_file
    from .harness.record import summarise
    from .harness.team import DEFAULT_ONTOLOGIES, Fault, Team, TeamSpec, draw_tasks

    ontologies = Path(args.ontologies) if args.ontologies else DEFAULT_ONTOLOGIES
    try:
        faults = tuple(
            Fault.parse(action, text)
            for action in ("kill", "restart", "stop", "resume")
            for text in getattr(args, action, None) or ()
        )
        spec = TeamSpec(
            robots=args.robots, mode=args.mode, transport=args.transport, strategy=args.strategy,
            query_wire=args.query_wire, ontologies=ontologies,
            time_scale=args.time_scale, replication=getattr(args, "replication", 2), faults=faults,
            security=not getattr(args, "insecure", False),
            credentials=None if getattr(args, "credentials", None) is None else Path(args.credentials),
            discovery=getattr(args, "discovery", "static"),
        )
        if getattr(args, "task_list", None):
            tasks = list(args.task_list)
        elif args.tasks_file:
            tasks = read_tasks_file(args.tasks_file)
        else:
            if args.tasks < 1:
                raise UserError("--tasks must be at least 1")
            tasks = draw_tasks(args.tasks, ontologies, seed=args.seed)
    except ValueError as exc:  # TeamSpec's checks; a FeederError (tasks file) reaches main as it is
        raise UserError(str(exc)) from None
    if not tasks:
        raise UserError("no tasks to run")

    def progress(bar: tqdm, record: TaskRecord) -> None:
        bar.update()
        if args.quiet:
            return
        bar.write(_task_lines(record, getattr(args, "verbose_costs", False)), file=sys.stdout)
        sys.stdout.flush()

    # Ctrl-C and SIGTERM (kill, a CI timeout) stop the robots: cancel this
    # task so that Team.launch's clean-up runs.  Ctrl-C reaches the robots
    # too (one process group), so a failure the feeder sees meanwhile is the
    # interrupt's doing, not the team's.
    loop = asyncio.get_running_loop()
    this_task = asyncio.current_task()
    stopped_by: int | None = None

    def on_signal(sig: int) -> None:
        nonlocal stopped_by
        stopped_by = sig
        if this_task is not None:
            this_task.cancel()

    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, on_signal, sig)
    try:
        async with Team.launch(spec, notice=lambda line: print(line, flush=True)) as team:
            print(f"team up: {', '.join(f'{r} {e}' for r, e in team.endpoints.items())}", flush=True)
            scheme = {"coap": "OSCORE keyed by EDHOC", "zmq": "CurveZMQ", "zenoh": "mutual TLS with team certificates"}[
                spec.transport] if spec.secure else ""
            print("security: " + (f"{scheme}, team access policy" if spec.secure else "none"), flush=True)
            # A live bar (tasks done, rate, time left) on a terminal's stderr only; the
            # per-task lines go to stdout above it, so a log or a pipe gets just those.
            with tqdm(total=len(tasks), unit="task", desc="tasks", file=sys.stderr, leave=False,
                      disable=True if args.quiet else None) as bar:
                record = await team.run(tasks, lambda r: progress(bar, r))
    except (FeederError, asyncio.CancelledError) as exc:  # TeamError is a FeederError
        if stopped_by is None:
            if isinstance(exc, asyncio.CancelledError):
                raise
            print(f"coapkb: team run failed: {exc}", file=sys.stderr)
            return 1
        print(f"coapkb: {'interrupted' if stopped_by == signal.SIGINT else 'terminated'}; robots stopped",
              file=sys.stderr)
        return 128 + stopped_by
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
    print()
    print(summarise(record))
    if args.record:
        Path(args.record).write_text(json.dumps(record.to_dict(), indent=2) + "\n", encoding="utf-8")
        print(f"record written to {args.record}")
    return 1 if record.disputed else 0


def _task_lines(record, costs: bool = False) -> str:  # record: TaskRecord
    """What the feeder saw of one task, as ``coapkb team`` and ``coapkb feed``
    print it; ``costs``: a second line with every robot's cost."""
    if record.skipped:
        outcome = "skipped: no such object"
    elif record.errors:
        outcome = "ERROR " + "; ".join(f"{r}: {e}" for r, e in record.errors.items())
    elif record.unavailable is not None:
        outcome = f"cannot be done: {record.unavailable}"
    else:
        outcome = f"-> {record.assigned_to or 'nobody can'}"
    if record.reassigned_from is not None:
        outcome += f" (again: task {record.reassigned_from})"
    if record.joined:
        outcome += f" [joined again: {', '.join(record.joined)}]"
    if record.absent:
        outcome += f" [down: {', '.join(record.absent)}; epoch {max(record.epochs.values(), default=0)}]"
    agreed = "" if record.agreed else "  DISAGREEMENT " + str(record.decisions)
    lines = [f"[cluster {record.cluster}] task {record.seq:>3} {record.object:<28} {outcome} "
             f"({record.coordination_s * 1000:.0f} ms){agreed}"]
    if costs and record.costs:
        text = ", ".join(
            f"{r}: {record.reasons.get(r, '-') if c is None else f'{c:.2f} Wh'}" for r, c in record.costs.items()
        )
        lines.append(f"      costs: {text}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- feed


def _add_feed(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "feed",
        help="feed tasks to robots started by hand (coapkb agent --config DIR/RobotN.toml), as the team's feeder",
        description="Reads the robots' TOML files in --team (their endpoints, clusters and key directory), "
        "checks that every robot answers, posts the tasks in order and prints what each robot decided. "
        "Example: examples/three-robots/README.md",
    )
    p.add_argument("--team", required=True, metavar="DIR", help="the folder holding the robots' TOML files")
    p.add_argument("--tasks-file", required=True, metavar="FILE", help="one object name per line")
    p.add_argument("--timeout", type=float, default=120.0, metavar="SECONDS",
                   help="how long one task's decisions may take (default 120)")
    p.add_argument("--answer-timeout", type=float, default=10.0, metavar="SECONDS",
                   help="how long each robot has to answer before feeding starts (default 10)")
    p.add_argument("--costs", action="store_true", help="also print every robot's cost for each task")
    p.set_defaults(run=_feed)


async def _feed(args: argparse.Namespace) -> int:
    from .feeder import FateCounts, Feeder, read_tasks_file
    from .feeder.team_folder import read_team_folder

    if not args.timeout > 0 or not args.answer_timeout > 0:
        raise UserError("--timeout and --answer-timeout must be positive")
    team = read_team_folder(args.team, task_timeout_s=args.timeout)
    tasks = read_tasks_file(args.tasks_file)
    if not tasks:
        raise UserError(f"no tasks in {args.tasks_file}")
    security = team.security()
    print(f"feeding {len(tasks)} task(s) to {', '.join(f'{r} {e}' for r, e in team.roster.endpoints.items())}"
          + ("" if security is None else f" (keys: {team.credentials})"), flush=True)
    async with Feeder.open(team.roster, team.settings, security) as feeder:
        await feeder.check_ready(args.answer_timeout, {r: f"is it running? start it with: {team.start_command(r)}" for r in team.files})
        outcome = await feeder.feed(tasks, lambda record: print(_task_lines(record, args.costs), flush=True))
    disputed = [t for t in outcome.tasks if not t.agreed]
    print(f"{FateCounts.of(outcome.tasks).line()}; "
          f"coordination {outcome.coordination_s:.2f} s, completion {outcome.completion_s:.2f} s")
    return 1 if disputed else 0


# --------------------------------------------------------------------------- query

FORMAT_ACCEPT = {"cbor": ContentFormat.CBOR, "json": ContentFormat.JSON}


def _add_query(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "query",
        help="query a robot: SPARQL text, or a named query URI",
        description="Examples:\n"
        "  coapkb query coap://127.0.0.1:5683 'SELECT * WHERE { ?s ?p ?o } LIMIT 3'\n"
        "  coapkb query 'coap://127.0.0.1:5683/kb/q/object-exists?name=Gucci_bag_14'",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("uri", help="robot (coap://, zmq://, zenoh:// or zenoh+udp://HOST:PORT), or a /kb/q/NAME?param=value URI")
    p.add_argument("sparql", nargs="?", help="query text; @FILE reads a file, - reads stdin")
    p.add_argument("--accept", choices=tuple(FORMAT_ACCEPT), default="cbor", help="answer format on the wire")
    p.add_argument("--format", choices=("table", "json", "csv"), default="table", help="output format")
    p.add_argument("--method", choices=("fetch", "post", "get"), default="fetch")
    p.add_argument("--timeout", type=float, default=30.0, metavar="SECONDS", help="give up after this long")
    _add_credentials(p, "operator")
    p.add_argument("--peer", metavar="NAME", help="the team member serving at URI (needed over zmq; checked over coap)")
    p.set_defaults(run=_query)


def _read_query_text(arg: str | None) -> str | None:
    if arg is None:
        return None
    if arg == "-":
        return sys.stdin.read()
    if arg.startswith("@"):
        try:
            return Path(arg[1:]).read_text(encoding="utf-8")
        except OSError as exc:
            raise UserError(f"cannot read query file {arg[1:]}: {exc.strerror}") from None
    return arg


async def _query(args: argparse.Namespace) -> int:
    from .kb.client import KBClient, QueryFailed
    from .kb.results import GraphResult
    from .transport import TransportError, open_client

    parts = urlsplit(args.uri if "://" in args.uri else f"coap://{args.uri}")
    peer = _endpoint(f"{parts.scheme}://{parts.netloc}", parts.scheme)
    text = _read_query_text(args.sparql)
    named = parts.path.startswith("/kb/q/")
    if named and text:
        raise UserError("give either a named query URI or SPARQL text, not both")
    if not named and not text:
        raise UserError("no query: give SPARQL text (or @FILE, or -) or a /kb/q/NAME URI")
    if parts.path not in ("", "/") and not named:
        raise UserError(f"unexpected path {parts.path!r}: use the robot's base URI or /kb/q/NAME")
    transport = await open_client(peer.scheme, security=_client_security(args, peer))
    client = KBClient(transport, timeout=args.timeout)
    accept = FORMAT_ACCEPT[args.accept]
    try:
        if named:
            result = await client.named(peer, parts.path.rsplit("/", 1)[1], dict(parse_qsl(parts.query)), accept=accept)
        else:
            result = await client.sparql(peer, text or "", accept=accept, method=Method(args.method.upper()))
    except QueryFailed as exc:
        print(f"coapkb: {peer} answered {exc}", file=sys.stderr)
        return 1
    except TransportError as exc:
        print(f"coapkb: {exc}", file=sys.stderr)
        return 1
    finally:
        await transport.aclose()
    sys.stdout.write(render(result, args.format))
    if args.format == "csv" and getattr(result, "truncated", False):
        # The table's footer and SPARQL-JSON's "truncated" say so; CSV has no room for it.
        shown = len(result.triples if isinstance(result, GraphResult) else result.rows)  # type: ignore[union-attr]
        print(f"coapkb: {peer} truncated the answer at its row limit: the CSV holds its first {shown} rows",
              file=sys.stderr)
    return 0


# --------------------------------------------------------------------------- bench


def _add_bench(sub: argparse._SubParsersAction) -> None:
    from .bench import run as bench

    p = sub.add_parser(
        "bench",
        help="benchmark systems on kernel-emulated slow, lossy links (root); one CSV row per run",
        description="Each run puts every robot, the central server and the task feeder in its own network "
        "namespace behind a tbf shaper and a loss rule (docs/link-emulation.md, docs/benchmarks.md).",
    )
    bench.add_arguments(p)
    p.set_defaults(run=_bench)


async def _bench(args: argparse.Namespace) -> int:
    from .bench import run as bench

    try:
        return await bench.main(args)
    except ValueError as exc:
        raise UserError(str(exc)) from None


# --------------------------------------------------------------------------- output

WELL_KNOWN_PREFIXES = {
    "obj": OBJECT_NS,
    "loc": LOCATION_NS,
    "cap": CAPABILITY_NS,
    "rdf": "http://www.w3.org/1999/02/22-rdf-syntax-ns#",
    "rdfs": "http://www.w3.org/2000/01/rdf-schema#",
    "owl": "http://www.w3.org/2002/07/owl#",
    "xsd": "http://www.w3.org/2001/XMLSchema#",
}


def render(result, fmt: str) -> str:  # result: QueryResult
    """A query result as text: an aligned table, SPARQL-JSON, or SPARQL CSV."""
    from .kb.results import AskResult, GraphResult, SelectResult

    if fmt == "json":
        return json.dumps(json.loads(codec.encode_json(result)), indent=2) + "\n"
    if isinstance(result, AskResult):
        return ("true" if result.value else "false") + "\n"
    if isinstance(result, GraphResult):
        header, rows = ["subject", "predicate", "object"], [list(t) for t in result.triples]
    else:
        assert isinstance(result, SelectResult)
        header, rows = list(result.variables), [list(r) for r in result.rows]
    if fmt == "csv":
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\r\n")  # SPARQL 1.1 CSV uses CRLF
        writer.writerow(header)
        writer.writerows([["" if t is None else str(t) for t in row] for row in rows])
        return out.getvalue()
    cells = [[_short(t) for t in row] for row in rows]
    widths = [max([len(h)] + [len(r[i]) for r in cells]) for i, h in enumerate(header)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(header, widths)).rstrip()]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip() for row in cells]
    truncated = getattr(result, "truncated", False)
    lines.append(f"({len(rows)} row{'s' if len(rows) != 1 else ''}{', truncated by the server' if truncated else ''})")
    return "\n".join(lines) + "\n"


def _short(term) -> str:
    from rdflib.term import BNode, Literal, URIRef

    if term is None:
        return ""
    if isinstance(term, URIRef):
        for prefix, ns in WELL_KNOWN_PREFIXES.items():
            if term.startswith(ns):
                return f"{prefix}:{term[len(ns):]}"
        return f"<{term}>"
    if isinstance(term, BNode):
        return f"_:{term}"
    assert isinstance(term, Literal)
    return str(term) + (f"@{term.language}" if term.language else "")


# --------------------------------------------------------------------------- main


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="coapkb", description="Semantic knowledge bases for robot teams over CoAP")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in COMMANDS:
        add(sub)
    return parser


COMMANDS: list[Callable[[argparse._SubParsersAction], None]] = [
    _add_demo, _add_team, _add_feed, _add_serve, _add_agent, _add_query, _add_bench, _add_keys,
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
