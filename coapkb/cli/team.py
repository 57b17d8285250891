"""``coapkb team`` and ``coapkb demo``: a whole team on this machine, robots
as processes, fed in order; and the line a task's outcome prints as."""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import signal
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from ..transport import SCHEMES
from .common import Parser, UserError, require_folder_of, until_signalled

if TYPE_CHECKING:
    from tqdm import tqdm

    from ..feeder import TaskRecord
    from ..feeder.tasks import Entry
    from ..harness.record import TeamRecord
    from ..harness.recording import RunRecorder
    from ..harness.team import Team, TeamSpec

#: The seed's example task (Fig. 4), a few more picks, and one object that
#: does not exist, which every robot must skip.
DEMO_TASKS = ("Gucci_bag_14", "Nonexistent_widget_1")
#: How often a recorded run samples the robots' statistics (they serve one
#: snapshot for 5 s): the series of ``/robots/traffic``.
STATS_EVERY_S = 2.0


def add_team(sub: argparse._SubParsersAction[Parser]) -> None:
    p = sub.add_parser("team", help="run a whole team locally: robots as processes, tasks fed in order")
    p.add_argument("--robots", type=int, default=3, help="team size, a multiple of 3 (clusters of three)")
    tasks = p.add_mutually_exclusive_group(required=True)
    tasks.add_argument("--tasks", type=int, metavar="N",
                       help="draw N objects from the Object KB: each once, then again, each later draw "
                            "after a delivery of the object back to its shelf (see --no-restock)")
    tasks.add_argument("--tasks-file", metavar="FILE",
                       help="one object name per line, or 'restock OBJECT': a delivery back to its shelf")
    p.add_argument("--no-restock", dest="restock", action="store_false",
                   help="with --tasks: no deliveries; an object drawn again is skipped as picked")
    p.add_argument("--seed", type=int, default=1, help="seed for --tasks")
    p.add_argument("--mode", choices=("distributed", "central"), default="distributed")
    p.add_argument("--transport", choices=SCHEMES, default="coap")
    p.add_argument("--strategy", choices=("compute-by-all", "compute-and-communicate"), default="compute-by-all")
    p.add_argument("--query-wire", choices=("compact", "seed"), default="compact")
    p.add_argument("--ontologies", default=None, metavar="DIR", help="directory with the three .owl files")
    p.add_argument("--time-scale", type=float, default=50.0, help="simulated seconds per wall-clock second")
    p.add_argument("--replication", type=int, default=2, metavar="R",
                   help="robots of a cluster holding each KB module (1-3, default 2: one may fail)")
    # WHEN: S seconds after the first task is fed (12s), or once the robot's cluster decided task N (taskN).
    p.add_argument("--kill", action="append", default=[], metavar="ROBOT@WHEN",
                   help="SIGKILL a robot at WHEN: Robot4@12s, or Robot4@task3 after its cluster decided task 3 "
                        "(the same on any machine; repeatable)")
    p.add_argument("--restart", action="append", default=[], metavar="ROBOT@WHEN",
                   help="start a killed robot again at WHEN; it joins the team at the next task (repeatable)")
    p.add_argument("--stop", action="append", default=[], metavar="ROBOT@WHEN",
                   help="SIGSTOP a robot at WHEN: cut off with its state intact (repeatable)")
    p.add_argument("--resume", action="append", default=[], metavar="ROBOT@WHEN",
                   help="SIGCONT a stopped robot at WHEN; it finds itself fenced off and picks nothing "
                        "the others took over (repeatable)")
    p.add_argument("--discovery", choices=("static", "rd"), default="static",
                   help="how robots find their teammates: static (each config lists its cluster, default) or rd "
                        "(each config lists the robot alone; it registers in a Resource Directory the feeder "
                        "hosts and looks its cluster up there; coap only)")
    p.add_argument("--record", metavar="OUT.json|OUT.mcap",
                   help="write the run's record here: JSON, or an MCAP file Foxglove opens (by the extension)")
    p.add_argument("--foxglove", metavar="[HOST:]PORT",
                   help="serve the run live to Foxglove (WebSocket protocol) while it runs; host 127.0.0.1 by default")
    p.add_argument("--keep-serving", action="store_true",
                   help="with --foxglove: once the run is over, go on serving it until Ctrl-C (time to open a viewer)")
    kb = p.add_mutually_exclusive_group()
    kb.add_argument("--read-only", dest="writable", action="store_false",
                    help="the robots' KBs stay as the files load them and refuse writes (the paper's workflow; "
                         "default: writable, see --writable)")
    kb.add_argument("--writable", dest="writable", action="store_true",
                    help="the default: the robots' KBs take writes (coapkb update) and replicate them among the "
                         "holders; the robots write their picks, positions and what they do not find")
    p.set_defaults(writable=True)
    p.add_argument("--data-dir", metavar="DIR",
                   help="keep each robot's writes in DIR/ROBOT (kept after the run; "
                        "default: in the run's temporary folder)")
    p.add_argument("--misplace", action="append", default=[], metavar="OBJECT",
                   help="the object is not where the KB says: the robot sent finds the shelf empty (repeatable)")
    p.add_argument("--insecure", action="store_true",
                   help="no OSCORE/EDHOC (coap) or CurveZMQ (zmq) and no access policy (default: on, throwaway team keys)")
    p.add_argument("--credentials", metavar="DIR", help="use this team key directory (coapkb keys) instead of throwaway keys")
    p.add_argument("--quiet", action="store_true", help="no per-task progress lines")
    p.set_defaults(run=_team)


def add_demo(sub: argparse._SubParsersAction[Parser]) -> None:
    p = sub.add_parser("demo", help="the main job: 3 robots on loopback do the seed's example tasks")
    p.add_argument("--transport", choices=SCHEMES, default="coap")
    p.add_argument("--insecure", action="store_true", help="no OSCORE/EDHOC (default: on, throwaway keys)")
    p.add_argument("--record", metavar="OUT.json", help="write the run's record here")
    p.set_defaults(run=_demo)


async def _demo(args: argparse.Namespace) -> int:
    from ..harness.team import DEFAULT_ONTOLOGIES, draw_tasks

    drawn = draw_tasks(4, DEFAULT_ONTOLOGIES, seed=7, exclude=DEMO_TASKS)
    # The seed's bag, four more, the bag again (picked by then: skipped) and an object nobody has.
    tasks = [DEMO_TASKS[0], *drawn, DEMO_TASKS[0], *DEMO_TASKS[1:]]
    print("Demo: a team of 3 robots, each KB module on two of them "
          "(Robot1: Location+Object, Robot2: Object+Capability, Robot3: Capability+Location)")
    print("on loopback, each a separate process, over " + args.transport + "; tasks: " + ", ".join(tasks))
    print("Each robot runs the seed's four queries per task and computes every robot's cost (Wh);")
    print("the cheapest capable robot gets the task; all robots must agree.")
    print("Each pick and each robot's new place is written into the Location KB: the bag's second task is skipped.\n")
    team_args = argparse.Namespace(
        robots=3, tasks=None, tasks_file=None, seed=1, mode="distributed", transport=args.transport,
        strategy="compute-by-all", query_wire="compact", ontologies=None,
        time_scale=50.0, record=args.record, quiet=False, task_list=tasks, verbose_costs=True,
        insecure=args.insecure, writable=True,
    )
    return await _team(team_args)


def _spec_and_tasks(args: argparse.Namespace) -> tuple[TeamSpec, list[Entry]]:
    """The team and its task list from the command line, or a :class:`UserError`."""
    from ..feeder import read_tasks_file
    from ..feeder.tasks import with_restocks
    from ..harness.team import DEFAULT_ONTOLOGIES, Fault, TeamSpec, draw_tasks

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
            kb_writable=getattr(args, "writable", True),
            misplaced=tuple(getattr(args, "misplace", None) or ()),
            data_dir=None if getattr(args, "data_dir", None) is None else Path(args.data_dir),
        )
        if getattr(args, "task_list", None):
            tasks = list(args.task_list)
        elif args.tasks_file:
            tasks = read_tasks_file(args.tasks_file)
        else:
            if args.tasks < 1:
                raise UserError("--tasks must be at least 1")
            drawn = draw_tasks(args.tasks, ontologies, seed=args.seed)
            tasks = with_restocks(drawn) if getattr(args, "restock", True) else drawn
    except ValueError as exc:  # TeamSpec's checks; a FeederError (tasks file) reaches main as it is
        raise UserError(str(exc)) from None
    if spec.secure and spec.credentials is not None and not (spec.credentials / "team.json").is_file():
        # Said here, not by the first robot, of the configuration file the
        # run wrote for it in a temporary folder (removed by then).
        raise UserError(f"--credentials {args.credentials}: no team.json in {spec.credentials.resolve()}; "
                        f"make the team's keys with: coapkb keys --team-dir {args.credentials}")
    if spec.data_dir is not None and not spec.kb_writable:
        raise UserError("--data-dir keeps the robots' writes: a --read-only team makes none")
    if not tasks:
        raise UserError("no tasks to run")
    return spec, tasks


def _security_line(spec: TeamSpec) -> str:
    if not spec.secure:
        return "security: none"
    from ..security import mechanism_for

    return f"security: {mechanism_for(spec.transport).title}, team access policy"


async def _team(args: argparse.Namespace) -> int:
    from ..feeder import FeederError

    spec, tasks = _spec_and_tasks(args)
    keep_serving = getattr(args, "keep_serving", False)  # coapkb demo has no live view
    if keep_serving and args.foxglove is None:
        raise UserError("--keep-serving goes with --foxglove [HOST:]PORT")
    if args.record:
        require_folder_of(Path(args.record), "--record")
    recorder = _recorder(args, spec)
    interruption = _Interruption()
    logger = logging.getLogger("coapkb")
    if recorder is not None:
        logger.addHandler(recorder.log_handler)
        if recorder.server is not None:
            print(f"foxglove: live on ws://{args.foxglove_at[0]}:{recorder.server.port}", flush=True)
    outcome = _TeamOutcome()
    holding = False
    try:
        await _run_team(args, spec, tasks, recorder, outcome)
    except (FeederError, asyncio.CancelledError) as exc:  # TeamError is a FeederError
        if interruption.signal is None:
            if isinstance(exc, asyncio.CancelledError):
                raise
            print(f"coapkb: team run failed: {exc}", file=sys.stderr)
            return 1
        print(f"coapkb: {'interrupted' if interruption.signal == signal.SIGINT else 'terminated'}; robots stopped",
              file=sys.stderr)
        return 128 + interruption.signal
    finally:
        interruption.remove()
        if recorder is not None:
            logger.removeHandler(recorder.log_handler)
            if outcome.record is not None:
                recorder.finished(outcome.record)
            holding = keep_serving and outcome.record is not None and interruption.signal is None
            recorder.close(keep_serving=holding)
    record = outcome.record
    assert record is not None  # the run ended without an error
    _print_outcome(args, spec, outcome, record, recorder)
    if holding and recorder is not None:
        await _serve_until_stopped(recorder, args.foxglove_at[0])
    return 1 if record.disputed else 0


class _Interruption:
    """Ctrl-C and SIGTERM (kill, a CI timeout) while the team runs: the
    signal kept and the running task cancelled, so that Team.launch's
    clean-up stops the robots.  Ctrl-C reaches the robots too (one process
    group), so a failure the feeder sees meanwhile is the interrupt's
    doing, not the team's."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        #: The signal that stopped the run, or None.
        self.signal: int | None = None
        self._task = asyncio.current_task()
        self._loop = asyncio.get_running_loop()
        for sig in self.SIGNALS:
            self._loop.add_signal_handler(sig, self._on_signal, sig)

    def _on_signal(self, sig: int) -> None:
        self.signal = sig
        if self._task is not None:
            self._task.cancel()

    def remove(self) -> None:
        for sig in self.SIGNALS:
            self._loop.remove_signal_handler(sig)


@dataclass
class _TeamOutcome:
    """What a team run gave, kept as it comes (the recording is told of
    the record even when the team's stop is interrupted)."""

    record: TeamRecord | None = None
    #: Deliveries made back to the shelves.
    restocked: int = 0
    #: The robots' positions in the Location KB, start and now (a writable distributed team).
    moved: str | None = None


async def _run_team(args: argparse.Namespace, spec: TeamSpec, tasks: list[Entry], recorder: RunRecorder | None,
                    outcome: _TeamOutcome) -> None:
    """Start the team, feed it the tasks under a progress bar, and keep what
    the run gives in ``outcome``; the team is stopped on the way out."""
    from tqdm import tqdm

    from ..feeder.tasks import task_count
    from ..harness.team import Team

    async with Team.launch(spec, notice=lambda line: print(line, flush=True)) as team:
        print(f"team up: {', '.join(f'{r} {e}' for r, e in team.endpoints.items())}", flush=True)
        print(_security_line(spec), flush=True)
        if spec.discovery == "rd":
            print("discovery: each robot found its cluster in the feeder's Resource Directory (RFC 9176)",
                  flush=True)
        # A live bar (tasks done, rate, time left) on a terminal's stderr only; the
        # per-task lines go to stdout above it, so a log or a pipe gets just those.
        with tqdm(total=task_count(tasks), unit="task", desc="tasks", file=sys.stderr, leave=False,
                  disable=True if args.quiet else None) as bar:
            outcome.record = await team.run(tasks, lambda r: _task_done(args, bar, recorder, r),
                                            on_state=None if recorder is None else recorder.robot_state,
                                            on_stats=None if recorder is None else (STATS_EVERY_S, recorder.traffic))
        if spec.kb_writable and spec.mode == "distributed":
            outcome.moved = await _positions_line(team)
        outcome.restocked = team.restocked


def _task_done(args: argparse.Namespace, bar: tqdm, recorder: RunRecorder | None, record: TaskRecord) -> None:
    """One task decided: the bar moves on, its line is printed (not with
    ``--quiet``) and the recording is told."""
    bar.update()
    if not args.quiet:
        bar.write(task_lines(record, getattr(args, "verbose_costs", False)), file=sys.stdout)
        sys.stdout.flush()
    if recorder is not None:
        recorder.task(record)


def _print_outcome(args: argparse.Namespace, spec: TeamSpec, outcome: _TeamOutcome, record: TeamRecord,
                   recorder: RunRecorder | None) -> None:
    """The run's summary, its deliveries and the robots' positions, and
    where its record went (written here when it is JSON)."""
    from ..harness.record import summarise

    print()
    print(summarise(record))
    if restocked := outcome.restocked:
        where = "in the KB and in the world" if spec.kb_writable and spec.mode == "distributed" else "in the world"
        print(f"restocked {restocked} object{'s' if restocked != 1 else ''} (delivered back to their shelves {where})")
    if spec.kb_writable and spec.mode == "distributed":
        print(outcome.moved)
    if args.record and recorder is not None and recorder.path is not None:
        print(f"recording written to {args.record} ({recorder.messages} messages)")
    elif args.record:
        Path(args.record).write_text(json.dumps(record.to_dict(), indent=2) + "\n", encoding="utf-8")
        print(f"record written to {args.record}")


async def _serve_until_stopped(recorder: RunRecorder, host: str) -> None:
    """``--keep-serving``: the live server stays up with the whole run until Ctrl-C or SIGTERM."""
    assert recorder.server is not None
    try:
        await until_signalled(f"foxglove: the run is over; still serving it on ws://{host}:{recorder.server.port} "
                              "until Ctrl-C")
    finally:
        recorder.close()


def _recorder(args: argparse.Namespace, spec: TeamSpec) -> RunRecorder | None:
    """The run's recording (``--record X.mcap``, ``--foxglove``), or None."""
    return open_recorder(args, spec.robot_ids, spec.ontologies, robots=spec.robots, mode=spec.mode,
                         transport=spec.transport, strategy=spec.strategy, writable=spec.kb_writable,
                         misplaced=list(spec.misplaced), time_scale=spec.time_scale, seed=getattr(args, "seed", None))


def open_recorder(args: argparse.Namespace, robot_ids: list[str], location_kb: Path,
                  **settings: object) -> RunRecorder | None:
    """``--record X.mcap`` and ``--foxglove [HOST:]PORT``: the run's
    :class:`~coapkb.harness.recording.RunRecorder`, or None without them
    (``args.foxglove_at`` is set to the live server's host and port)."""
    record = getattr(args, "record", None)
    mcap = Path(record) if record and record.endswith(".mcap") else None
    live = getattr(args, "foxglove", None)
    args.foxglove_at = None if live is None else parse_host_port(live, "--foxglove")
    if mcap is None and live is None:
        return None
    from ..harness.recording import RecordingError, RunRecorder, run_metadata, warehouse

    layout, docks = warehouse(location_kb)
    try:
        return RunRecorder(mcap, args.foxglove_at, robot_ids, layout, docks,
                           metadata=run_metadata(sys.argv, **settings))
    except RecordingError as exc:
        raise UserError(str(exc)) from None


def parse_host_port(text: str, option: str, host: str = "127.0.0.1") -> tuple[str, int]:
    """``[HOST:]PORT``, or a :class:`UserError` naming ``option``."""
    given, _, port = text.rpartition(":")
    if not (port.isascii() and port.isdigit()):
        raise UserError(f"{option} takes [HOST:]PORT, got {text!r}")
    if int(port) > 65535:
        raise UserError(f"{option}: port {int(port)} out of range (0-65535)")
    return given.strip("[]") or host, int(port)


async def _positions_line(team: Team) -> str:
    """Where the Location KB put each robot at the start, and where it says
    they are now (the robots wrote it as they worked)."""
    from ..errors import CoapkbError
    from ..harness.team import robot_starts

    starts = robot_starts(team.spec.ontologies)
    try:
        now = await team.kb_positions()
    except CoapkbError as exc:  # TransportError and QueryFailed among them
        return f"positions in the Location KB: not read ({exc})"
    return "positions in the Location KB (aisle, rack), start -> now: " + ", ".join(
        f"{r} ({starts[r]['aisle']}, {starts[r]['rack']}) -> {now[r]}" for r in team.spec.robot_ids if r in now)


def task_lines(record: TaskRecord, costs: bool = False) -> str:
    """What the feeder saw of one task, as ``coapkb team`` and ``coapkb feed``
    print it; ``costs``: a second line with every robot's cost."""
    if record.skipped:
        outcome = f"skipped: {record.skip_reason or 'no such object'}"
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
    # As the summary counts them: a disagreement is a task that failed with
    # no robot's error (an error is shown as such; robots that all skip in
    # different membership epochs still skip).
    agreed = ""
    if record.fate == "failed" and not record.errors:
        agreed = ("  DISAGREEMENT " + str(record.decisions) if len(set(record.decisions.values())) > 1
                  else "  DISAGREEMENT on the membership epoch " + str(record.epochs))
    lines = [f"[cluster {record.cluster}] task {record.seq:>3} {record.object:<28} {outcome} "
             f"({record.coordination_s * 1000:.0f} ms){agreed}"]
    if costs and record.costs:
        text = ", ".join(
            f"{r}: {record.reasons.get(r, '-') if c is None else f'{c:.2f} Wh'}" for r, c in record.costs.items()
        )
        lines.append(f"      costs: {text}")
    return "\n".join(lines)
