"""``coapkb sim --shrink FILE`` and ``--replay FILE``: a violating run
reduced to the smallest case that still breaks the same invariant, written
to a file, and that file run again (:mod:`coapkb.sim.case`,
:mod:`coapkb.sim.shrink`)."""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, TextIO

from .common import UserError

if TYPE_CHECKING:
    from ..sim import KBCache, RunResult, SimSpec
    from ..sim.case import SimCase

#: Options that go with ``--replay`` (the others describe a run: its file does).
WITH_REPLAY = frozenset({"help", "replay", "shrink", "shrink_budget", "trace", "quiet", "jobs"})


def add_case_options(p: argparse.ArgumentParser) -> None:
    """``--shrink``, ``--shrink-budget`` and ``--replay``, once every other
    option of ``coapkb sim`` is added: those others then default to None, so
    that one given with ``--replay`` is refused (:func:`run_defaults` puts
    their defaults back otherwise)."""
    p.add_argument("--shrink", metavar="FILE",
                   help="with --seed S (or --replay CASE): if the run breaks an invariant, reduce its fault events, "
                        "tasks, team and link faults while the same invariant breaks first, and write the smallest "
                        "case to FILE")
    p.add_argument("--shrink-budget", type=float, default=60.0, metavar="SECONDS",
                   help="wall-clock seconds --shrink may take (default 60): the smallest case by then is written")
    p.add_argument("--replay", metavar="FILE", help="run the case in FILE (as --shrink writes it) again, exactly")
    deferred = {a.dest: (a.default, a.option_strings[0]) for a in p._actions
                if a.dest not in WITH_REPLAY and a.option_strings}
    p.set_defaults(**{dest: None for dest in deferred}, run_defaults=deferred)


def run_defaults(args: argparse.Namespace) -> None:
    """The run options' defaults, for a run that is not a replay."""
    for dest, (default, _) in args.run_defaults.items():
        if getattr(args, dest) is None:
            setattr(args, dest, default)


def check_budget(args: argparse.Namespace) -> None:
    if args.shrink_budget <= 0:
        raise UserError("--shrink-budget must be positive")


def counted(n: int, what: str) -> str:
    """``1 run``, ``2 runs``."""
    return f"{n:,} {what}" if n == 1 else f"{n:,} {what}s"


def _writes(runs: Sequence[RunResult]) -> str:
    """The operator's writes (one may go to two holders at once: two
    requests), and how many requests were acknowledged (2.04)."""
    writes = sum(len({w.label for w in r.writes}) for r in runs)
    requests = sum(len(r.writes) for r in runs)
    acked = sum(1 for r in runs for w in r.writes if w.status == "2.04")
    return f"{counted(writes, 'write')} ({counted(requests, 'request')}, {acked:,} acknowledged)"


def written(run: RunResult) -> str:
    """The operator's writes of a run and whether its replicas converged:
    ``; 5 writes (6 requests, 5 acknowledged), the replicas agreed`` (nothing without writes)."""
    if not run.writes:
        return ""
    agreed = "agreed" if run.converged_at is not None else "never agreed"
    return f"; {_writes([run])}, the replicas {agreed}"


def report_run(run: RunResult, quiet: bool) -> None:
    """One run's line: its violations, what excused it, or (unless ``quiet``) that it was ok."""
    if run.violations:
        print(f"seed {run.seed} ({run.schedule}): VIOLATION " + " | ".join(run.violations), flush=True)
    elif run.excused and not quiet:
        print(f"seed {run.seed} ({run.schedule}): excused " + " | ".join(run.excused), flush=True)
    elif not quiet:
        print(f"seed {run.seed}: ok, {run.fates}{written(run)} ({run.sim_s:.1f} simulated s)", flush=True)


def closing_line(runs: Sequence[RunResult], violating: int, started: float) -> str:
    """``sim: R runs, V violations, S simulated s in W wall s`` and, with
    writes, how many there were and in how many runs the replicas agreed."""
    with_writes = [r for r in runs if r.writes]
    replicated = ""
    if with_writes:
        agreed = sum(1 for r in with_writes if r.converged_at is not None)
        replicated = (f"; {_writes(with_writes)}, the replicas agreed in {agreed} of "
                      f"{counted(len(with_writes), 'run')} with writes")
    from ..sim.invariants import median_caught_up, median_decided

    median, caught_up = median_decided(runs), median_caught_up(runs)
    decided = f"; tasks decided in {median:.2f} s (median)" if median is not None else ""
    if caught_up is not None:
        stale = sum(len(r.stale_reads) for r in runs)
        replicated += (f"; restarted holders caught up in {caught_up:.2f} s (median), "
                       f"{stale:,} {'query' if stale == 1 else 'queries'} answered meanwhile")
    return (f"sim: {counted(len(runs), 'run')}, {counted(violating, 'violation')}, "
            f"{sum(r.sim_s for r in runs):,.0f} simulated s in {time.monotonic() - started:,.1f} wall s"
            f"{decided}{replicated}")


def replay_case(args: argparse.Namespace) -> int:
    """``--replay FILE``: run the case again and print its result line (with
    ``--shrink OUT``: reduce it further)."""
    from ..sim import KBCache, summary
    from ..sim.case import SimCase
    from ..sim.shrink import first_violation, replay

    check_budget(args)
    given = [flag for dest, (_, flag) in args.run_defaults.items() if getattr(args, dest) is not None]
    if given:
        raise UserError(f"--replay runs the case its file holds: drop {', '.join(given)}")
    started = time.monotonic()
    case = SimCase.load(args.replay)
    here = os.environ.get("PYTHONHASHSEED")
    if case.hash_seed is not None and case.hash_seed != here:
        print(f"sim: note: {args.replay} was written under PYTHONHASHSEED={case.hash_seed}, this run has "
              f"{here or 'a random one'}: sets of names iterate in another order, so the run may differ")
    kbs = KBCache()
    if args.shrink:
        return _shrink(args, case, kbs, started, expect=None)
    full = _traced(args.trace, lambda out: replay(case, kbs, out))
    now = first_violation(full)  # from the whole history: the summary keeps none of it
    run = summary(full)
    report_run(run, False)
    if case.violates is not None:
        if now is not None and now.check == case.violates:
            print(f"sim: {args.replay} breaks {case.violates} again, as when it was written")
        else:
            print(f"sim: {args.replay} broke {case.violates} when it was written; now "
                  + (f"{now.check} first" if now is not None else "no invariant"))
    return _closing([run], started)


def shrink_seed(args: argparse.Namespace, spec: SimSpec, started: float) -> int:
    """``--seed S --shrink FILE``: run the seed; if it breaks an invariant, shrink it."""
    from dataclasses import replace

    from ..sim import KBCache, run_checked, summary
    from ..sim.case import SimCase
    from ..sim.shrink import first_violation

    check_budget(args)
    if args.seed is None:
        raise UserError("--shrink reduces one run: give --seed S (or --replay CASE)")
    kbs = KBCache()
    run = run_checked(spec, args.seed, kbs)
    report_run(summary(run), False)
    violation = first_violation(run)
    if violation is None:
        print(f"sim: seed {args.seed} breaks no invariant: nothing to shrink")
        return _closing([run], started)
    case = replace(SimCase.drawn(spec, args.seed, kbs), violates=violation.check, finding=violation.finding)
    return _shrink(args, case, kbs, started, expect=violation.check)


def _shrink(args: argparse.Namespace, case: SimCase, kbs: KBCache, started: float, expect: str | None) -> int:
    from ..sim import summary
    from ..sim.shrink import replay, shrink_case

    budget = args.shrink_budget - (time.monotonic() - started)
    shrunk = shrink_case(case, kbs=kbs, budget_s=budget, progress=lambda line: print(line, flush=True),
                         expect=expect)
    if shrunk is None:
        print(f"sim: {args.replay} breaks no invariant: nothing to shrink")
        return _closing([], started)
    shrunk.case.save(args.shrink)
    run = shrunk.run if not args.trace else _traced(args.trace, lambda out: replay(shrunk.case, kbs, out))
    report_run(summary(run), False)
    how = "no reduction left to try" if shrunk.complete else "the budget ran out"
    print(f"sim: shrunk {shrunk.original.describe_size()} to {shrunk.case.describe_size()}, still breaking "
          f"{shrunk.violation.check} first, in {shrunk.runs} runs and {shrunk.elapsed_s:.1f} s ({how})")
    print(f"sim: wrote {args.shrink}; run it again with: coapkb sim --replay {args.shrink}")
    print(f"sim: {counted(shrunk.runs, 'run')}, {counted(shrunk.violating, 'violation')}, "
          f"{shrunk.sim_s:,.0f} simulated s in {time.monotonic() - started:,.1f} wall s")
    return 1


def _traced(path: str | None, run: Callable[[TextIO | None], RunResult]) -> RunResult:
    """``run(trace)``, its trace written to ``path`` if given."""
    if path is None:
        return run(None)
    try:
        with open(path, "w", encoding="utf-8") as out:
            return run(out)
    except OSError as exc:
        raise UserError(f"cannot write {path}: {exc.strerror}") from None


def _closing(runs: list[RunResult], started: float) -> int:
    """The closing lines, as every ``coapkb sim`` prints them; 1 if a run broke an invariant."""
    violating = sum(1 for r in runs if r.violations)
    excused = sum(len(r.excused) for r in runs)
    if excused:
        print(f"sim: {counted(excused, 'finding')} excused by their schedules, in "
              f"{counted(sum(1 for r in runs if r.excused), 'run')}")
    print(closing_line(runs, violating, started))
    return 1 if violating else 0
