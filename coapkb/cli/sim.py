"""``coapkb sim``: the whole team in the deterministic simulator, one run
per seed, each judged against the invariants (docs/simulation.md)."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from pathlib import Path

from .common import Parser, UserError
from .sim_case import add_case_options, closing_line, counted, replay_case, report_run, run_defaults, shrink_seed


def add_sim(sub: argparse._SubParsersAction[Parser]) -> None:
    p = sub.add_parser("sim", help="run the team in the deterministic simulator under seeded faults")
    p.add_argument("--robots", type=int, default=3, help="team size, a multiple of 3 (clusters of three)")
    p.add_argument("--tasks", type=int, default=10, help="tasks per run, drawn from the Object KB by the seed")
    p.add_argument("--seeds", default="1-100", metavar="A-B",
                   help="run every seed from A to B (default 1-100); also N or a list: 2,65,100-120")
    p.add_argument("--seed", type=int, metavar="S", help="run seed S alone (with --trace: write its trace)")
    p.add_argument("--faults", default="mixed", metavar="LIST",
                   help="fault kinds a run may draw: kill, freeze, partition, starve, loss[=P], burst[=P], dup[=P], "
                        "jitter[=S]; mixed = all of them; none = no faults (default mixed); by name only: forge, "
                        "crash (a power cut), rejoin (a restarted robot cut off from its cluster), bounce (killed and "
                        "started again within half a second), swarm; P is a "
                        "probability (loss=0.2) or a percentage (loss=20%%)")
    p.add_argument("--strategy", choices=("compute-by-all", "compute-and-communicate"), default="compute-by-all")
    p.add_argument("--writes", type=int, default=0, metavar="N",
                   help="an operator writes N times to random robots' KBs during each run (replication checked)")
    p.add_argument("--storage", action="store_true",
                   help="every robot keeps its writes in a data folder: kills keep it (and may tear its journal's "
                        "tail), restarts restore from it; with crash in --faults, every holder of a module dies at once")
    p.add_argument("--observers", type=int, default=0, metavar="N",
                   help="with --writes: N clients observe the written knowledge of a holder each, as coapkb query "
                        "--observe does; each must show what its robot's KB shows once the replicas agree")
    p.add_argument("--waiting-max", type=int, default=0, metavar="N",
                   help="with --writes: each replica takes at most N dots waiting past a gap (default 10,000, "
                        "never reached in a run); a holder at the bound refuses a push (5.03) and takes it later")
    p.add_argument("--ties", action="store_true",
                   help="every robot of a cluster starts at the same place: cost ties, decided by the tie-break")
    p.add_argument("--ontologies", default=None, metavar="DIR", help="directory with the three .owl files")
    p.add_argument("--jobs", type=int, default=None, metavar="N", help="worker processes (default: the cores)")
    p.add_argument("--trace", metavar="FILE", help="with --seed: write every message, fault and pick in order")
    p.add_argument("--quiet", action="store_true", help="only violating seeds and the summary line")
    p.add_argument("-x", "--exitfirst", action="store_true",
                   help="stop at the first seed that violates an invariant (the seeds after it are not run)")
    p.add_argument("--decide-within", type=float, default=None, metavar="S",
                   help="progress oracle: fail if the median task of all the runs took longer than S "
                        "simulated seconds to decide")
    p.add_argument("--catch-up-within", type=float, default=None, metavar="S",
                   help="catch-up oracle (with --writes): fail if the median restarted holder of all the runs "
                        "took longer than S simulated seconds to show what its co-holders showed at its restart")
    add_case_options(p)
    p.set_defaults(run=_sim)


def _seeds(text: str) -> list[int]:
    """``1-500``, ``7``, or a list of both: ``2,65,100-120``."""
    seeds: list[int] = []
    for part in text.split(","):
        first, sep, last = part.strip().partition("-")
        try:
            a, b = int(first), int(last) if sep else int(first)
        except ValueError:
            raise UserError(f"--seeds expects A-B (like 1-500), numbers, or a list of both, got {text!r}") from None
        if b < a:
            raise UserError(f"--seeds {part}: the range is empty")
        seeds += range(a, b + 1)
    return seeds


def _replayable(args: argparse.Namespace) -> None:
    """Runs replay byte for byte only under one hash seed (the iteration
    order of sets of names): start again under PYTHONHASHSEED=0 if needed,
    when run as the command (not from a test calling main())."""
    if os.environ.get("PYTHONHASHSEED") == "0" or sys.argv[1:] != args.argv:
        return
    sys.stdout.flush()
    os.execve(sys.executable, [sys.executable, "-m", "coapkb", *args.argv], {**os.environ, "PYTHONHASHSEED": "0"})


async def _sim(args: argparse.Namespace) -> int:
    from ..harness.team import DEFAULT_ONTOLOGIES
    from ..sim import FaultMix, KBCache, SimSpec, run_checked, run_many, summary

    _replayable(args)
    if args.replay is not None:
        return replay_case(args)
    run_defaults(args)
    if args.robots < 3 or args.robots % 3:
        raise UserError(f"--robots must be a multiple of 3, got {args.robots}")
    if args.tasks < 1:
        raise UserError(f"--tasks must be at least 1, got {args.tasks}")
    if args.trace and args.seed is None:
        raise UserError("--trace writes one run's trace: give --seed S")
    if args.exitfirst and (args.decide_within is not None or args.catch_up_within is not None):
        raise UserError("--exitfirst leaves seeds out, and --decide-within and --catch-up-within judge every run "
                        "together: give one or the other")
    if args.writes < 0:
        raise UserError("--writes must not be negative")
    for option, bound in (("--decide-within", args.decide_within), ("--catch-up-within", args.catch_up_within)):
        if bound is not None and not bound > 0:
            raise UserError(f"{option} must be positive, got {bound:g}")
    if args.observers < 0:
        raise UserError("--observers must not be negative")
    if args.observers and not args.writes:
        raise UserError("--observers watch what the operator writes: give --writes N too")
    if args.waiting_max < 0:
        raise UserError("--waiting-max must not be negative")
    if args.waiting_max and not args.writes:
        raise UserError("--waiting-max bounds what the operator's writes leave waiting: give --writes N too")
    if args.catch_up_within is not None and not args.writes:
        raise UserError("--catch-up-within times what restarted holders catch up with: give --writes N too")
    spec = SimSpec(robots=args.robots, tasks=args.tasks, strategy=args.strategy, faults=FaultMix.parse(args.faults),
                   writes=args.writes, ties=args.ties, storage=args.storage, observers=args.observers,
                   waiting_max=args.waiting_max,
                   ontologies=Path(args.ontologies) if args.ontologies else DEFAULT_ONTOLOGIES)
    started = time.monotonic()
    if args.shrink:
        return shrink_seed(args, spec, started)
    if args.seed is not None:
        kbs = KBCache()
        if args.trace:
            try:
                with open(args.trace, "w", encoding="utf-8") as out:
                    runs = [summary(run_checked(spec, args.seed, kbs, out))]
            except OSError as exc:
                raise UserError(f"cannot write {args.trace}: {exc.strerror}") from None
        else:
            runs = [summary(run_checked(spec, args.seed, kbs))]
    else:
        runs = []
        # Closed on a break: the pool's workers and their scratch folder end here.
        with contextlib.closing(run_many(spec, _seeds(args.seeds), args.jobs)) as results:
            for run in results:
                runs.append(run)
                report_run(run, args.quiet)
                if args.exitfirst and run.violations:
                    break
    if args.seed is not None:
        report_run(runs[0], args.quiet)
    violating = sum(1 for r in runs if r.violations)
    excused = sum(len(r.excused) for r in runs)
    if excused:
        print(f"sim: {counted(excused, 'finding')} excused by their schedules (a starved CPU, lost answers, a pick "
              f"unreported when its robot died, a write's last copy in a killed robot's memory, a pick after a "
              f"power cut of the cluster's majority), "
              f"in {counted(sum(1 for r in runs if r.excused), 'run')}")
    from ..sim.invariants import check_catch_up, check_progress

    slow = [f"sim: VIOLATION {what}: {finding}" for what, bound, check in (
        ("progress", args.decide_within, check_progress), ("catch-up", args.catch_up_within, check_catch_up))
        if runs and bound is not None and (finding := check(runs, bound)) is not None]
    for line in slow:
        print(line)
    print(closing_line(runs, violating, started))
    return 1 if violating or slow else 0
