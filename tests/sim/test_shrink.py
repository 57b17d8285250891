"""Shrinking a violating run to the smallest case that still breaks the
same invariant, the case file, and replaying it (``coapkb sim --shrink``,
``--replay``).

The reductions are checked first against a made-up run (what breaks is
decided from the case alone, so no simulation is needed), then end to
end on the simulator with a bug planted in the robots: nobody is ever
declared down, so a robot killed while tasks remain stalls the run."""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from coapkb.agent.failure_detector import FailureDetector
from coapkb.cli import main
from coapkb.sim import FaultMix, KBCache, SimSpec, SimulationError, run_checked
from coapkb.sim.case import CaseFileError, SimCase, mix_text
from coapkb.sim.faults import ACTIONS, FaultEvent
from coapkb.sim.run import RunResult
from coapkb.sim.shrink import ddmin, first_violation, replay, shrink, shrink_case, units


@pytest.fixture(scope="module")
def kbs() -> KBCache:
    return KBCache()


def _event(at: float, action: str, target: str, amount: float = 0.0, other: tuple[str, ...] = (),
           until_s: float = 0.0) -> FaultEvent:
    return FaultEvent(at, action, (target,), amount, other, until_s)


# --------------------------------------------------------------------------- the pieces


def test_a_fault_goes_with_what_ends_it() -> None:
    events = [
        _event(0.2, "starve", "Robot7", amount=0.3, until_s=1.0),
        _event(0.5, "kill", "Robot1"),
        _event(0.8, "cut", "feeder", other=("Robot1", "Robot2")),
        _event(0.9, "restart", "Robot1"),
        _event(1.0, "cut", "feeder", other=("Robot1", "Robot2")),
        _event(1.5, "heal", "feeder"),
        _event(1.6, "freeze", "Robot2"),
        _event(1.7, "heal", "feeder"),
        _event(2.0, "resume", "Robot2"),
        _event(3.0, "kill", "Robot3"),
        _event(4.0, "heal", "Robot9"),
    ]
    # The feeder's two overlapping cuts end in the order they began; a kill
    # may stay without a restart; an end without its fault stays alone.
    assert units(events) == [(0,), (1, 3), (2, 5), (4, 7), (6, 8), (9,), (10,)]


def test_ddmin_finds_a_one_minimal_subset() -> None:
    tried: list[list[int]] = []

    def test(items: list[int]) -> bool:
        tried.append(items)
        return {3, 7, 8} <= set(items)

    assert ddmin(list(range(12)), test) == [3, 7, 8]
    assert len(tried) < 40


# --------------------------------------------------------------------------- the reductions, on made-up runs


def _made_up(case: SimCase, kbs: KBCache | None = None, trace: object = None) -> RunResult:
    """A run decided by the case alone: its team and link faults in ``schedule``."""
    run = RunResult(case.seed, f"{case.robots} robots, {case.faults}", None, None, [], [])
    run.events, run.fed, run.sim_s = list(case.events), list(case.tasks), 1.0
    run.violations = [finding for check in MADE_UP_CHECKS for finding in check(run)]
    return run


def check_few_tasks(run: RunResult) -> Iterable[str]:
    """Listed first: fewer than three tasks without a Pear."""
    if len(run.fed) < 3 and "Pear" not in run.fed:
        yield "too few tasks"


def check_planted(run: RunResult) -> Iterable[str]:
    """The planted bug: an Apple, Robot1 killed, then Robot2 frozen for 0.4 s or more."""
    kills = [e for e in run.events if e.action == "kill" and e.targets == ("Robot1",)]
    freezes = [e for e in run.events if e.action == "freeze" and e.targets == ("Robot2",)]
    resumes = [e for e in run.events if e.action == "resume" and e.targets == ("Robot2",)]
    if "Apple" in run.fed and kills and freezes and resumes and round(resumes[0].at_s - freezes[0].at_s, 6) >= 0.4:
        yield "planted"


#: The made-up runs' invariants, and the shrinker's options that run and judge them.
MADE_UP_CHECKS = (check_few_tasks, check_planted)
MADE_UP = {"runner": _made_up, "checks": MADE_UP_CHECKS}


ALL_EVENTS = (
    _event(0.2, "starve", "Robot7", amount=0.3, until_s=1.0),
    _event(0.5, "kill", "Robot1"),
    FaultEvent(0.8, "cut", ("Robot5",), other=("Robot4", "Robot6")),
    _event(0.9, "restart", "Robot1"),
    _event(1.0, "freeze", "Robot2"),
    _event(2.0, "heal", "Robot5"),
    FaultEvent(2.5, "cut", ("feeder",), other=tuple(f"Robot{i}" for i in range(1, 10))),
    _event(3.0, "heal", "feeder"),
    _event(4.2, "resume", "Robot2"),
)
FRUIT = ("Fig", "Apple", "Kiwi", "Plum", "Pear", "Lime", "Date", "Yuzu")


def test_every_reduction_keeps_the_same_invariant_broken_first() -> None:
    case = SimCase(seed=7, robots=9, strategy="compute-by-all", faults="kill,freeze,loss=0.05,dup=0.02,jitter=0.02",
                   tasks=FRUIT, events=ALL_EVENTS)
    lines: list[str] = []
    shrunk = shrink_case(case, budget_s=600, progress=lines.append, **MADE_UP)
    assert shrunk is not None and shrunk.complete
    small = shrunk.case
    assert (shrunk.violation.check, small.violates) == ("check_planted", "check_planted")
    # Removing Fig or Kiwi as well would break check_few_tasks first: another bug.
    assert small.tasks == ("Fig", "Apple", "Kiwi")
    assert small.robots == 3 and small.faults == "kill,freeze"
    # Robot1 restarted still (Robot2 of its cluster is frozen later), sooner;
    # the freeze halved down to the shortest that still breaks it.
    assert [(e.action, e.targets) for e in small.events] == [
        ("kill", ("Robot1",)), ("restart", ("Robot1",)), ("freeze", ("Robot2",)), ("resume", ("Robot2",))]
    kill, restart, freeze, resume = small.events
    assert kill.at_s == 0.5 and restart.at_s < 0.9 and freeze.at_s == 1.0 and resume.at_s == pytest.approx(1.4)
    assert shrunk.original == replace(case, violates="check_planted", finding="planted") and small.seed == case.seed
    assert lines[0].startswith("shrink: seed 7 breaks check_planted") and "robots (" in lines[-1]


def test_a_kill_whose_cluster_is_left_alone_loses_its_restart() -> None:
    events = (_event(0.5, "freeze", "Robot2"), _event(1.5, "resume", "Robot2"),
              _event(2.0, "kill", "Robot1"), _event(3.0, "restart", "Robot1"))
    case = SimCase(seed=1, robots=3, strategy="compute-by-all", faults="none", tasks=("Apple", "Pear"), events=events)
    shrunk = shrink_case(case, **MADE_UP)
    assert shrunk is not None
    assert [e.action for e in shrunk.case.events] == ["freeze", "resume", "kill"]


def test_the_budget_keeps_the_smallest_case_so_far_and_a_case_must_break_what_it_should() -> None:
    case = SimCase(seed=7, robots=9, strategy="compute-by-all", faults="none", tasks=FRUIT, events=ALL_EVENTS)
    shrunk = shrink_case(case, budget_s=0, **MADE_UP)
    assert shrunk is not None and not shrunk.complete and shrunk.runs == 1
    assert shrunk.case.events == case.events and shrunk.case.tasks == case.tasks
    with pytest.raises(SimulationError, match="does not break check_few_tasks"):
        shrink_case(case, expect="check_few_tasks", **MADE_UP)
    assert shrink_case(SimCase(seed=7, robots=3, strategy="compute-by-all", faults="none", tasks=FRUIT,
                               events=()), **MADE_UP) is None


# --------------------------------------------------------------------------- the case file


def test_a_case_file_holds_the_whole_run(tmp_path: Path) -> None:
    case = SimCase(seed=7, robots=9, strategy="compute-and-communicate", faults="kill,loss=0.123456789",
                   tasks=FRUIT, events=ALL_EVENTS, writes=3, settings={"query_timeout_s": 2.5},
                   violates="check_planted", finding="planted", hash_seed="0")
    path = tmp_path / "case.json"
    case.save(path)
    assert SimCase.load(path) == case
    spec = SimCase.load(path).spec()
    assert spec.faults.loss == 0.123456789 and spec.query_timeout_s == 2.5 and spec.tasks == len(FRUIT)
    assert spec.task_list == FRUIT and spec.schedule == ALL_EVENTS and spec.strategy == "compute-and-communicate"
    assert json.loads(path.read_text())["events"][2] == {
        "at_s": 0.8, "action": "cut", "targets": ["Robot5"], "amount": 0.0, "other": ["Robot4", "Robot6"],
        "until_s": 0.0}


def test_a_case_file_takes_every_action_a_schedule_draws(tmp_path: Path, kbs: KBCache) -> None:
    """Power cuts and forged syncs too: the shrunk case of simulator seed
    50615 was written and then refused ("unknown action 'forge'")."""
    spec = SimSpec(robots=3, tasks=4, faults=FaultMix.parse("crash,forge,swarm"), storage=True)
    drawn = {e.action for seed in range(1, 6) for e in SimCase.drawn(spec, seed, kbs).events}
    assert {"crash", "forge"} <= drawn <= set(ACTIONS)
    path = tmp_path / "case.json"
    case = SimCase(seed=7, robots=3, strategy="compute-by-all", faults="none", tasks=FRUIT,
                   events=tuple(FaultEvent(1.0, action, ("Robot1",), other=("Robot2",)) for action in ACTIONS))
    case.save(path)
    assert SimCase.load(path) == case


def test_a_case_is_what_the_seed_draws_with_a_swarm_mix_and_the_settings_that_differ(kbs: KBCache) -> None:
    mix = FaultMix.parse("mixed,swarm,loss=0.2")
    assert FaultMix.parse(mix_text(mix)) == mix and "swarm" in mix_text(mix)
    spec = SimSpec(tasks=4, faults=mix, replication=3, query_timeout_s=2.0)
    case = SimCase.drawn(spec, 5, kbs)
    assert case.settings == {"replication": 3, "query_timeout_s": 2.0} and len(case.tasks) == 4 and case.events
    again = case.spec()
    assert again.replication == 3 and again.faults == mix and again.task_list == case.tasks
    assert SimCase.drawn(again, 5, kbs) == case  # the explicit schedule is the one the seed drew


def test_a_case_replays_its_seed_exactly_traps_and_all(kbs: KBCache) -> None:
    """Seed 16 draws a trap that springs: the run's events hold the freeze
    it sprang, the case only the trap, and the case's run is the seed's."""
    spec = SimSpec(robots=3, tasks=6, faults=FaultMix.parse("mixed,swarm"))
    case = SimCase.drawn(spec, 16, kbs)
    seed_run, case_run = run_checked(spec, 16, kbs), replay(case, kbs)
    assert any(e.action.endswith("-picking") for e in case.events) and len(seed_run.events) > len(case.events)
    assert (case_run.events, case_run.picks, case_run.sim_s, case_run.messages, case_run.violations) == (
        seed_run.events, seed_run.picks, seed_run.sim_s, seed_run.messages, seed_run.violations)


def _case_text(**changes: object) -> str:
    raw = SimCase(seed=7, robots=3, strategy="compute-by-all", faults="none", tasks=("Apple",),
                  events=(_event(0.5, "kill", "Robot1"),)).to_dict()
    raw.update(changes)
    return json.dumps(raw)


@pytest.mark.parametrize(("text", "needle"), [
    (None, "no case file"),
    ("{not json", "is not JSON: Expecting property name"),
    ("[1, 2]", "expected a JSON object"),
    (json.dumps({"seed": 1}), "not a simulation case"),
    (_case_text(version=9), "version 9 is not one this coapkb reads"),
    (_case_text(seed="7"), "'seed' must be a whole number"),
    (_case_text(robots=4), "multiple of 3"),
    (_case_text(faults="meteor"), "unknown fault 'meteor'"),
    (_case_text(tasks=[]), "non-empty list of object names"),
    (_case_text(events=[{"at_s": 1, "action": "explode", "targets": ["Robot1"]}]), "unknown action 'explode'"),
    (_case_text(events=[{"at_s": 1, "action": "kill", "targets": ["Robot4"]}]), "names 'Robot4'"),
    (_case_text(events=[{"at_s": "soon", "action": "kill", "targets": ["Robot1"]}]), "'at_s' must be a number"),
    (_case_text(events=[{"action": "kill", "targets": ["Robot1"]}]), "'at_s' is missing"),
    (_case_text(colour="red"), "unknown key 'colour'"),
    (_case_text(settings={"colour": 1}), "unknown setting 'colour'"),
    (_case_text(settings={"replication": "two"}), "'replication' must be a whole number, got 'two'"),
])
def test_a_bad_case_file_is_refused_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                text: str | None, needle: str) -> None:
    path = tmp_path / "case.json"
    if text is not None:
        path.write_text(text)
    with pytest.raises(CaseFileError, match=needle):
        SimCase.load(path)
    with pytest.raises(SystemExit) as exited:
        main(["sim", "--replay", str(path)])
    err = capsys.readouterr().err
    assert exited.value.code == 2 and needle in err and err.count("\n") == 1 and "Traceback" not in err, err


@pytest.mark.parametrize(("args", "needle"), [
    (["--replay", "case.json", "--robots", "3"], "--replay runs the case its file holds: drop --robots"),
    (["--replay", "case.json", "--seed", "3", "--faults", "kill"], "drop --seed, --faults"),
    (["--shrink", "out.json"], "give --seed S (or --replay CASE)"),
    (["--seed", "3", "--shrink", "out.json", "--shrink-budget", "0"], "--shrink-budget must be positive"),
])
def test_the_command_refuses_mixed_up_options(capsys: pytest.CaptureFixture[str], args: list[str],
                                              needle: str) -> None:
    with pytest.raises(SystemExit) as exited:
        main(["sim", *args])
    err = capsys.readouterr().err
    assert exited.value.code == 2 and needle in err and "Traceback" not in err, err


# --------------------------------------------------------------------------- end to end, with a planted bug


@pytest.fixture
def nobody_declared_down(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """The planted bug: a robot (or the feeder) never stops counting on a dead teammate."""
    async def never(self: FailureDetector, robot_id: str, reason: str) -> None:
        return None

    monkeypatch.setattr(FailureDetector, "declare_down", never)
    yield


def _result_lines(out: str) -> list[str]:
    return [line for line in out.splitlines() if line.startswith("seed ")]


@pytest.mark.usefixtures("nobody_declared_down")
def test_a_planted_violation_is_shrunk_written_and_replayed(tmp_path: Path, kbs: KBCache,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    schedule = (
        _event(0.3, "starve", "Robot5", amount=0.4, until_s=1.2),
        FaultEvent(0.4, "cut", ("Robot4",), other=("Robot5", "Robot6")),
        _event(0.6, "kill", "Robot1"),
        _event(0.9, "heal", "Robot4"),
        _event(1.0, "freeze", "Robot6"),
        _event(1.6, "resume", "Robot6"),
    )
    spec = SimSpec(robots=6, tasks=8, faults=FaultMix.parse("kill,freeze,loss=0.05,dup=0.02"), schedule=schedule)
    lines: list[str] = []
    # A budget that only bounds a hang: the shrinker stops when no cut helps
    # (on a quiet machine in about 20 s), so a busy machine shrinks as far.
    shrunk = shrink(spec, 3, kbs=kbs, budget_s=600, progress=lines.append)
    assert shrunk is not None, "the planted bug no longer breaks anything"
    broken = shrunk.violation.check
    assert shrunk.original.violates == broken and shrunk.case.violates == broken
    assert len(shrunk.original.events) == 6 and shrunk.original.robots == 6
    small = shrunk.case
    assert [(e.action, e.targets) for e in small.events] == [("kill", ("Robot1",))]
    assert small.robots == 3 and len(small.tasks) < 8 and small.seed == 3
    assert any("fewer events" in line for line in lines)

    path = tmp_path / "smallest.json"
    small.save(path)
    again = SimCase.load(path)
    assert again == small
    found = first_violation(replay(again, kbs))
    assert found is not None and found.check == broken

    # The command: shrinking a case further finds nothing left to cut, and
    # each replay prints the same result line.
    capsys.readouterr()
    further = tmp_path / "further.json"
    assert main(["sim", "--replay", str(path), "--shrink", str(further), "--shrink-budget", "300"]) == 1
    shrunk_out = capsys.readouterr().out
    assert SimCase.load(further).size == small.size
    assert main(["sim", "--replay", str(further)]) == 1
    replay_out = capsys.readouterr().out
    assert _result_lines(replay_out) == _result_lines(shrunk_out)[-1:] and "VIOLATION" in replay_out
    assert f"breaks {broken} again" in replay_out


@pytest.mark.usefixtures("nobody_declared_down")
def test_the_command_shrinks_a_seed(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Seed 25 draws a kill and a restart, two starved robots and duplicates."""
    path = tmp_path / "seed25.json"
    args = ["sim", "--robots", "3", "--tasks", "6", "--faults", "kill,freeze,starve,dup", "--seed", "25"]
    assert main([*args, "--shrink", str(path), "--shrink-budget", "300"]) == 1  # bounds a hang only
    out = capsys.readouterr().out
    first, smallest = _result_lines(out)[0], _result_lines(out)[-1]
    assert first.startswith("seed 25 (kill Robot1@") and "VIOLATION" in smallest
    assert f"wrote {path}" in out and out.rstrip().splitlines()[-1].startswith("sim: ")
    case = SimCase.load(path)
    assert case.seed == 25 and len(case.events) < 4 and case.events[0].action == "kill"
    assert main(["sim", "--replay", str(path)]) == 1
    assert _result_lines(capsys.readouterr().out) == [smallest]
