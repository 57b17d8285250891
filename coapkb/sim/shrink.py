"""The smallest run that still breaks an invariant (``coapkb sim --shrink``).

A violating seed's run is written as a :class:`~coapkb.sim.case.SimCase`
(its tasks and fault events explicit), then reduced for as long as the
reduced case still breaks the same invariant first: the first check of
:data:`coapkb.sim.invariants.CHECKS` that fails is the same one.  The
reductions, in the order tried:

* a shorter prefix of the task list (a binary search);
* fewer fault events: delta debugging (ddmin) over the events, a fault
  always together with what ends it (a kill with its restart, a freeze with
  its resume, a cut with its heal), so every freeze and partition still heals;
* fewer robots (9 -> 6 -> 3) when no event names a robot left out (a cut
  loses the left-out robots from its other side);
* no loss, bursts, duplicates or jitter on the links, one at a time;
* a killed robot never restarted, when no later event touches its cluster
  (at most one robot of a cluster out at a time, as every schedule keeps);
* shorter faults, each halved while the violation stays: an outage ended
  sooner, a starve or a trap armed for less time, a trap holding for less;
* fewer tasks (ddmin over the whole list);
* fewer operator writes.

The seed stays: it still drives the network's draws, the robots'
randomness, the operator's writes and, in swarm testing, the links'
amounts, so the smallest case replays exactly.  The passes repeat until
none reduces anything, or until the wall-clock budget runs out or the user
interrupts (the smallest case so far is the result).  Everything runs in
this process, one run at a time, so a test's monkeypatch applies to every
run.  A smaller case may break the same invariant another way (its
finding's text can change): each case keeps the finding it broke with.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from typing import TextIO, TypeVar

from . import invariants
from .case import SimCase, mix_text
from .faults import LINK_KINDS, FaultEvent, FaultMix
from .loop import SimulationError
from .run import KBCache, RunResult, SimSpec, run_seed

T = TypeVar("T")

#: A fault's closing event: the kill's restart, the freeze's resume, the cut's heal.
CLOSES = {"kill": "restart", "freeze": "resume", "cut": "heal"}
#: Faults are not shortened below this (simulated seconds).
MIN_DURATION_S = 0.1
DEFAULT_BUDGET_S = 60.0


@dataclass(frozen=True)
class Violation:
    """The first invariant a run broke: its check's name and its first finding."""

    check: str
    finding: str


#: An invariant's check, as :data:`~coapkb.sim.invariants.CHECKS` lists them.
Check = Callable[[RunResult], Iterable[invariants.Finding]]
#: What runs a case and judges it (:func:`replay`).
Runner = Callable[[SimCase, KBCache], RunResult]


def first_violation(run: RunResult, checks: Sequence[Check] | None = None) -> Violation | None:
    """The first check of ``checks`` (default :data:`~coapkb.sim.invariants.CHECKS`) that ``run`` fails, if any."""
    for invariant in invariants.CHECKS if checks is None else checks:
        for finding in invariant(run):
            if not isinstance(finding, invariants.Excused):
                return Violation(invariant.__name__, finding)
    return None


def replay(case: SimCase, kbs: KBCache | None = None, trace: TextIO | None = None) -> RunResult:
    """Run ``case`` and judge it (its ``violations`` filled in)."""
    return invariants.check(run_seed(case.spec(), case.seed, kbs or KBCache(), trace))


@dataclass
class Shrunk:
    """What shrinking found."""

    #: The case as the seed drew it, and the smallest one that breaks the same invariant.
    original: SimCase
    case: SimCase
    #: The invariant broken (by both), as the smallest case breaks it.
    violation: Violation
    #: The smallest case's run, judged.
    run: RunResult
    #: Runs made, how many broke an invariant (any), their simulated seconds and the wall-clock seconds taken.
    runs: int
    violating: int
    sim_s: float
    elapsed_s: float
    #: False when the budget ran out with reductions still left to try.
    complete: bool


def shrink(spec: SimSpec, seed: int, *, kbs: KBCache | None = None, budget_s: float = DEFAULT_BUDGET_S,
           progress: Callable[[str], None] | None = None) -> Shrunk | None:
    """Run seed ``seed`` of ``spec``; if it breaks an invariant, the smallest
    case found within ``budget_s`` wall-clock seconds (counted from the
    start) that breaks the same one first.  None: the seed holds every
    invariant.  ``progress`` gets a line at the start and at each reduction."""
    kbs = kbs or KBCache()
    started = time.monotonic()
    run = invariants.check(run_seed(spec, seed, kbs))
    violation = first_violation(run)
    if violation is None:
        return None
    case = SimCase.drawn(spec, seed, kbs)
    return shrink_case(case, kbs=kbs, budget_s=budget_s - (time.monotonic() - started), progress=progress,
                       expect=violation.check)


def shrink_case(case: SimCase, *, kbs: KBCache | None = None, budget_s: float = DEFAULT_BUDGET_S,
                progress: Callable[[str], None] | None = None, expect: str | None = None,
                runner: Runner | None = None, checks: Sequence[Check] | None = None) -> Shrunk | None:
    """The smallest case found within ``budget_s`` wall-clock seconds that
    breaks first the invariant ``case`` breaks first when run (None: it
    breaks none).  ``expect``: the check it must break first (the seed's, for
    a case written from a seed's run): :class:`SimulationError` if it does
    not, since the case would not replay the seed.  ``runner`` and
    ``checks``: what runs a case (:func:`replay`) and the invariants judged
    (:data:`~coapkb.sim.invariants.CHECKS`), for tests of the reductions."""
    shrinker = _Shrinker(case, kbs or KBCache(), budget_s, progress, expect)
    shrinker.runner, shrinker.checks = runner or replay, checks
    return shrinker.run()


class _OutOfBudget(Exception):
    """The budget ran out: stop and keep the smallest case so far."""


class _Shrinker:
    def __init__(self, case: SimCase, kbs: KBCache, budget_s: float, progress: Callable[[str], None] | None,
                 expect: str | None) -> None:
        self.kbs, self.budget_s, self.progress = kbs, budget_s, progress or (lambda _: None)
        self.expect = expect
        self.started = time.monotonic()
        self.deadline = self.started + budget_s
        #: Runs that broke an invariant (any), and the simulated seconds of all runs.
        self.violating = 0
        self.sim_s = 0.0
        self.runs = 0
        self.original = case
        self.best = case
        #: Every case tried (its content), and whether it broke the invariant.
        self.tried: dict[str, bool] = {}
        self.violation: Violation | None = None
        self.best_run: RunResult | None = None
        self.runner: Runner = replay
        self.checks: Sequence[Check] | None = None

    @property
    def elapsed_s(self) -> float:
        return time.monotonic() - self.started

    def run(self) -> Shrunk | None:
        run = self._run(self.original)
        violation = first_violation(run, self.checks)
        if self.expect is not None and (violation is None or violation.check != self.expect):
            raise SimulationError(f"seed {self.original.seed}'s run, written as a case, does not break {self.expect} "
                                  f"first again ({violation.check if violation else 'nothing'}): it does not replay")
        if violation is None:
            return None
        self.violation, self.best_run = violation, run
        self.best = replace(self.original, violates=violation.check, finding=violation.finding)
        self.original = self.best
        self.tried[self._key(self.best)] = True
        self.progress(f"shrink: seed {self.original.seed} breaks {violation.check}: {violation.finding}")
        self.progress(f"shrink: {self.best.describe_size()} to start with")
        complete = True
        try:
            changed = True
            while changed:
                before = self._key(self.best)
                for reduce in (self._prefix, self._events, self._robots, self._links, self._restarts,
                               self._durations, self._tasks, self._writes):
                    reduce()
                changed = self._key(self.best) != before
        except _OutOfBudget:
            complete = False
            self.progress(f"shrink: the budget of {self.budget_s:.0f} s ran out; keeping the smallest case so far")
        except KeyboardInterrupt:
            complete = False
            self.progress("shrink: interrupted; keeping the smallest case so far")
        assert self.best_run is not None
        last = first_violation(self.best_run, self.checks)
        assert last is not None
        return Shrunk(self.original, self.best, last, self.best_run, self.runs, self.violating, self.sim_s,
                      self.elapsed_s, complete)

    # ------------------------------------------------------------- one try

    @staticmethod
    def _key(case: SimCase) -> str:
        content = replace(case, violates=None, finding=None, hash_seed=None)
        return json.dumps(content.to_dict(), sort_keys=True)

    def _try(self, candidate: SimCase, what: str) -> bool:
        """Run ``candidate``; if it breaks the same invariant first, it is the smallest case now."""
        key = self._key(candidate)
        known = self.tried.get(key)
        if known is not None:
            return known
        if time.monotonic() >= self.deadline:
            raise _OutOfBudget
        try:
            run = self._run(candidate)
        except Exception as exc:  # noqa: BLE001 - a reduction the simulator cannot run is one that does not reproduce
            self.progress(f"shrink: a reduction ({what}) did not run: {type(exc).__name__}: {exc}")
            self.tried[key] = False
            return False
        found = first_violation(run, self.checks)
        assert self.violation is not None
        same = found is not None and found.check == self.violation.check
        self.tried[key] = same
        if same and found is not None:
            self.best = replace(candidate, violates=found.check, finding=found.finding)
            self.best_run = run
            self.progress(f"shrink: {self.best.describe_size()} ({what}; run {self.runs}, {self.elapsed_s:.1f} s)")
        return same

    def _run(self, case: SimCase) -> RunResult:
        self.runs += 1
        run = self.runner(case, self.kbs)
        self.violating += bool(run.violations)
        self.sim_s += run.sim_s
        return run

    # ------------------------------------------------------------- the reductions

    def _prefix(self) -> None:
        """The shortest prefix of the task list that still breaks it (a binary search)."""
        low, high = 1, len(self.best.tasks)
        while low < high:
            middle = (low + high) // 2
            if self._try(replace(self.best, tasks=self.best.tasks[:middle]), f"the first {middle} task{'s' * (middle != 1)}"):
                high = middle
            else:
                low = middle + 1

    def _tasks(self) -> None:
        start = self.best
        if len(start.tasks) < 2:
            return
        ddmin(list(range(len(start.tasks))),
              lambda kept: self._try(replace(start, tasks=tuple(start.tasks[i] for i in kept)), "fewer tasks"))

    def _events(self) -> None:
        start = self.best
        if not start.events:
            return

        def with_units(kept: list[tuple[int, ...]]) -> bool:
            indices = sorted(i for unit in kept for i in unit)
            return self._try(replace(start, events=tuple(start.events[i] for i in indices)), "fewer events")

        if with_units([]):
            return
        ddmin(units(start.events), with_units)

    def _robots(self) -> None:
        for robots in range(3, self.best.robots, 3):
            events = _for_team(self.best.events, robots)
            if events is not None and self._try(replace(self.best, robots=robots, events=events), f"{robots} robots"):
                return

    def _links(self) -> None:
        for kind in LINK_KINDS:
            parts = mix_text(FaultMix.parse(self.best.faults)).split(",")
            kept = [p for p in parts if p.partition("=")[0] != kind]
            if kept != parts:
                self._try(replace(self.best, faults=",".join(kept) or "none"), f"no {kind}")

    def _restarts(self) -> None:
        """A killed robot left dead, when no later event touches its cluster."""
        done = 0
        while True:
            events = self.best.events
            pairs = [u for u in units(events) if len(u) == 2 and events[u[0]].action == "kill"]
            if done >= len(pairs):
                return
            kill, restart = pairs[done]
            victim = events[kill].targets[0]
            touched = any(_cluster(t) == _cluster(victim)
                          for i, e in enumerate(events) if i > kill and i != restart for t in e.targets)
            left_dead = replace(self.best, events=events[:restart] + events[restart + 1:])
            if touched or not self._try(left_dead, f"{victim} not restarted"):
                done += 1  # else the pair is gone: the next one moved up

    def _durations(self) -> None:
        """Each fault halved in length while the violation stays (not below
        :data:`MIN_DURATION_S`): an outage ended sooner, a starve or a trap
        armed for less time, a trap holding its robot for less."""
        position = 0
        while position < len(units(self.best.events)):
            for way in ("closing", "window", "hold"):
                while True:
                    shorter = _shortened(self.best.events, position, way)
                    if shorter is None or not self._try(replace(self.best, events=shorter[0]), shorter[1]):
                        break
            position += 1

    def _writes(self) -> None:
        writes = self.best.writes
        if writes and not self._try(replace(self.best, writes=0), "no writes"):
            while writes > 1 and self._try(replace(self.best, writes=writes // 2), f"{writes // 2} writes"):
                writes //= 2


def units(events: Sequence[FaultEvent]) -> list[tuple[int, ...]]:
    """``events``' indices grouped into what must go together: a fault and
    the event that ends it (the first later restart, resume or heal of the
    same target); a starve, or an end without its fault, alone."""
    grouped: list[list[int]] = []
    opened: dict[tuple[str, str], list[list[int]]] = {}
    for index, event in enumerate(events):
        target = event.targets[0]
        closes = CLOSES.get(event.action)
        waiting = opened.get((event.action, target))
        if closes is not None:
            unit = [index]
            opened.setdefault((closes, target), []).append(unit)
            grouped.append(unit)
        elif waiting:
            waiting.pop(0).append(index)
        else:
            grouped.append([index])
    return [tuple(unit) for unit in grouped]


def _shortened(events: Sequence[FaultEvent], position: int, way: str) -> tuple[tuple[FaultEvent, ...], str] | None:
    """``events`` with unit ``position`` halved one ``way``: its closing event
    sooner, its window (``until_s``) shorter, or its hold (a trap's ``amount``)
    shorter; None if that is not its kind of duration or it is short already."""
    unit = units(events)[position]
    first = events[unit[0]]
    changed = list(events)
    if way == "closing" and len(unit) == 2:
        last = events[unit[1]]
        length = last.at_s - first.at_s
        changed[unit[1]] = replace(last, at_s=round(first.at_s + length / 2, 3))
    elif way == "window" and len(unit) == 1 and first.until_s > first.at_s:
        length = first.until_s - first.at_s
        changed[unit[0]] = replace(first, until_s=round(first.at_s + length / 2, 3))
    elif way == "hold" and first.action.endswith("-picking"):
        length = first.amount
        changed[unit[0]] = replace(first, amount=round(length / 2, 3))
    else:
        return None
    if length / 2 < MIN_DURATION_S:
        return None
    return tuple(sorted(changed, key=lambda e: e.at_s)), f"a shorter {first.action} of {first.targets[0]}"


def ddmin(items: list[T], test: Callable[[list[T]], bool]) -> list[T]:
    """Zeller's delta debugging: a 1-minimal sublist of ``items`` for which
    ``test`` holds (it holds for ``items``): removing any one item breaks it."""
    parts = 2
    while len(items) >= 2:
        chunks = list(_split(items, parts))
        reduced = False
        for chunk in chunks:
            if test(chunk):
                items, parts, reduced = chunk, 2, True
                break
        if not reduced and parts > 2:
            for i in range(len(chunks)):
                rest = [x for j, chunk in enumerate(chunks) if j != i for x in chunk]
                if test(rest):
                    items, parts, reduced = rest, max(parts - 1, 2), True
                    break
        if not reduced:
            if parts >= len(items):
                break
            parts = min(len(items), parts * 2)
    return items


def _split(items: list[T], parts: int) -> Iterator[list[T]]:
    for i in range(parts):
        yield items[len(items) * i // parts: len(items) * (i + 1) // parts]


def _robot_number(name: str) -> int | None:
    return int(name[5:]) if name.startswith("Robot") and name[5:].isdigit() else None


def _cluster(name: str) -> int | None:
    number = _robot_number(name)
    return None if number is None else (number - 1) // 3


def _for_team(events: Sequence[FaultEvent], robots: int) -> tuple[FaultEvent, ...] | None:
    """``events`` for a team of ``robots`` (cuts no longer naming the robots
    left out), or None if an event's target is left out."""
    def kept(name: str) -> bool:
        number = _robot_number(name)
        return number is None or number <= robots

    fitted = []
    for event in events:
        if not all(kept(t) for t in event.targets):
            return None
        other = tuple(o for o in event.other if kept(o))
        if event.other and not other:
            return None
        fitted.append(dataclasses.replace(event, other=other))
    return tuple(fitted)
