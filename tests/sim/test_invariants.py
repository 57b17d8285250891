"""The checker: each invariant finds what breaks it in a made-up history,
and says nothing of a good one."""

from __future__ import annotations

import logging

from support import ONTOLOGIES

from coapkb.feeder.record import TaskRecord
from coapkb.harness.record import TeamRecord
from coapkb.kb.live import LiveKB, wall_ms
from coapkb.kb.store import KnowledgeBase
from coapkb.sim.faults import FaultEvent
from coapkb.sim.invariants import check
from coapkb.sim.observed import FilesQuads, Grant, Take, of_module
from coapkb.sim.observers import ObserverView
from coapkb.sim.operator import WriteOp
from coapkb.sim.run import Pick, RunResult, _History
from coapkb.transport.base import TrafficCounters

CLUSTER = ["Robot1", "Robot2", "Robot3"]


def _task(seq: int, obj: str, to: str | None = "Robot1", **changes: object) -> TaskRecord:
    task = TaskRecord(object=obj, cluster=1, seq=seq, assigned_to=to,
                      decisions={r: to for r in CLUSTER}, epochs={r: 0 for r in CLUSTER}, members=list(CLUSTER))
    for name, value in changes.items():
        setattr(task, name, value)
    return task


def _run(tasks: list[TaskRecord], picks: list[Pick], **changes: object) -> RunResult:
    record = TeamRecord(mode="distributed", transport="coap", strategy="compute-by-all", query_wire="compact",
                        robots=list(CLUSTER), clusters=[list(CLUSTER)], tasks=tasks, coordination_s=1.0,
                        completion_s=2.0, robot_stats={}, feeder_traffic=TrafficCounters(), faults=[], down={})
    run = RunResult(seed=1, schedule="test", record=record, error=None, picks=picks, crashes=[],
                    fed=[t.object for t in tasks if t.reassigned_from is None])
    for name, value in changes.items():
        setattr(run, name, value)
    return check(run)


def _pick(robot: str, seq: int, obj: str, at_s: float = 1.0) -> Pick:
    return Pick(robot, 0, seq, obj, at_s)


def test_a_good_history_breaks_nothing() -> None:
    run = _run([_task(1, "A"), _task(2, "B", "Robot2")], [_pick("Robot1", 1, "A"), _pick("Robot2", 2, "B")])
    assert run.violations == [] and run.excused == []


def test_a_task_picked_twice_is_found() -> None:
    tasks = [_task(1, "A", orphaned="Robot1 down"), _task(2, "A", "Robot2", reassigned_from=1)]
    run = _run(tasks, [_pick("Robot1", 1, "A", 1.0), _pick("Robot2", 2, "A", 5.0)])
    assert any("executed 2 times" in v for v in run.violations), run.violations


def test_a_pick_its_dead_robot_never_reported_is_excused_not_hidden() -> None:
    tasks = [_task(1, "A", orphaned="Robot1 down"), _task(2, "A", "Robot2", reassigned_from=1)]
    picks = [_pick("Robot1", 1, "A", 1.0), _pick("Robot2", 2, "A", 5.0)]
    killed = [FaultEvent(1.1, "kill", ("Robot1",))]
    run = _run(tasks, picks, events=killed, reports={("Robot1", 0): [(0.5, 0), (1.05, 0)]})
    assert run.violations == [] and "killed 0.100s after its pick" in run.excused[0]
    reported = _run(tasks, picks, events=killed, reports={("Robot1", 0): [(1.05, 1)]})
    assert any("executed 2 times" in v for v in reported.violations)  # the feeder knew: no excuse


def test_a_pick_the_record_gives_to_another_robot_is_found() -> None:
    """Robot2 picked task 10, which the record gives to Robot1 (whose void
    decision the feeder counted), and the task went round again: the shelf
    had one take, and only the record shows it (simulator, rejoin seed 96)."""
    tasks = [_task(10, "A", "Robot1", orphaned="Robot1 dropped it unexecuted"),
             _task(31, "A", "Robot2", reassigned_from=10, not_found="Robot2 did not find it: gone")]
    run = _run(tasks, [_pick("Robot2", 10, "A", 1.0)])
    assert any("Robot2 as task 10 at 1.000s picked it, and the record gives it to Robot1" in v
               for v in run.violations), run.violations


def test_a_pick_a_skip_credits_at_its_own_task_is_no_finding() -> None:
    """Robot2 picked task 2 and died with Robot1 before the feeder had their
    decisions; Robot3 found the pick in the KB and skipped the task, naming
    Robot2: the record credits the pick (simulator seed 54366 of the
    storage profile, a false finding of the first form of this oracle)."""
    tasks = [_task(2, "A", None, skipped=True, skip_reason="picked by Robot2 at task 2", decisions={"Robot3": None})]
    run = _run(tasks, [_pick("Robot2", 2, "A", 1.0)])
    assert not any("record gives it" in v for v in run.violations + run.excused), run.violations


def test_a_pick_at_the_edge_of_an_exclusion_is_a_violation() -> None:
    """Robot1 picked task 10 under a lease from before, which Robot2 and
    Robot3 (a majority) decided without it and gave to Robot3: excused
    while the fence covered old tasks only (simulator seed 356 of the mixed
    profile); a lease is now granted per task, so it is a violation."""
    tasks = [_task(10, "A", "Robot3", members=["Robot2", "Robot3"], not_found="Robot3 did not find it: gone")]
    run = _run(tasks, [_pick("Robot1", 10, "A", 1.0)])
    assert run.excused == [] and any("had left the picker out" in v for v in run.violations), run.violations


def test_an_assigned_task_nobody_executed_is_found() -> None:
    run = _run([_task(1, "A")], [])
    assert run.violations == ["cluster 1 task 1 (A) was assigned to Robot1 and never executed"]


def test_fates_that_do_not_add_up_are_found() -> None:
    tasks = [_task(1, "A"), _task(3, "B"), _task(4, "A", reassigned_from=1)]
    run = _run(tasks, [_pick("Robot1", 1, "A"), _pick("Robot1", 3, "B")])
    found = " | ".join(run.violations)
    assert "have gaps or repeats" in found and "re-runs task 1, which was not reassigned" in found


def test_a_split_decision_and_an_epoch_going_back_are_found() -> None:
    split = _task(2, "B", decisions={"Robot1": "Robot1", "Robot2": "Robot1", "Robot3": None},
                  epochs={"Robot1": 1, "Robot2": 1, "Robot3": 1})
    back = _task(3, "C", epochs={"Robot1": 0, "Robot2": 0, "Robot3": 0})
    first = _task(1, "A", epochs={"Robot1": 1, "Robot2": 1, "Robot3": 1})
    run = _run([first, split, back], [_pick("Robot1", 1, "A"), _pick("Robot1", 3, "C")])
    found = " | ".join(run.violations)
    assert "task 2 of cluster 1 (B): decisions Robot1: Robot1 (epoch 1)" in found
    assert "Robot1's epoch went back from 1 (task 2) to 0 (task 3)" in found


def test_a_false_suspicion_under_starvation_is_excused_with_its_reason() -> None:
    split = _task(1, "A", decisions={"Robot1": "Robot1", "Robot2": "Robot1", "Robot3": None},
                  errors={"Robot3": "no state for task 0 from Robot1 within 10s"})
    starved = [FaultEvent(0.5, "starve", ("Robot3",), amount=0.2, until_s=3.0)]
    run = _run([split], [_pick("Robot1", 1, "A")], events=starved)
    assert run.violations == [] and "a false suspicion under CPU starvation (Robot3 starved)" in run.excused[0]


def test_a_split_after_a_kill_and_a_power_cut_took_a_majority_is_excused() -> None:
    """Robot3 killed, then a power cut took Robot1: two of three down, no
    majority left to decide (simulator, nine robots, seed 6043); the cut
    alone, or after Robot3 came back, leaves a majority, and the split stands."""
    split = _task(1, "A", decisions={"Robot1": "Robot1", "Robot2": "Robot1"}, epochs={"Robot1": 0, "Robot2": 1})
    cut = [FaultEvent(2.28, "crash", ("Robot7",), amount=2.0), FaultEvent(2.28, "kill", ("Robot1",))]
    killed = [FaultEvent(2.0, "kill", ("Robot3",))]
    back = [*killed, FaultEvent(2.1, "restart", ("Robot3",))]
    excused = _run([split], [_pick("Robot1", 1, "A")], events=[*killed, *cut])
    assert excused.violations == [] and "a power cut left a majority of the cluster down" in excused.excused[0]
    for events in (cut, [*back, *cut]):
        assert "task 1 of cluster 1 (A)" in " | ".join(_run([split], [_pick("Robot1", 1, "A")], events=events).violations)


def test_a_split_with_a_live_robot_left_out_is_a_false_suspicion_only_where_a_cut_explains_it() -> None:
    """Robot2 back from a cut left a live Robot3 out alone: Robot3's decision
    is void, no error names it, and Robot1 and Robot2 decide in different
    epochs (simulator, nine robots with partitions, seed 4246).  Excused as
    a false suspicion with the cut in the schedule, found without it."""
    split = _task(4, "D", to="Robot2", decisions={"Robot1": "Robot2", "Robot2": "Robot2"},
                  epochs={"Robot1": 0, "Robot2": 1}, members=["Robot1", "Robot2"],
                  absent={"Robot3": "left out of membership epoch 1 (its decision is void)"})
    picked = [_pick("Robot2", 4, "D")]
    cut = [FaultEvent(0.1, "cut", ("Robot2",), other=("Robot1", "Robot3")), FaultEvent(3.5, "heal", ("Robot2",))]
    excused = _run([split], picked, events=cut)
    assert excused.violations == [] and "a false suspicion of a robot cut off" in excused.excused[0]
    assert "task 4 of cluster 1 (D)" in " | ".join(_run([split], picked).violations)


def test_a_hang_a_crash_and_unbounded_state_are_found() -> None:
    run = _run([_task(1, "A")], [_pick("Robot1", 1, "A")], error="SimulationError: hung at 3.000 s",
               crashes=["Robot2: Task exception was never retrieved KeyError: 'x'"],
               bounds={"Robot1 tasks": (500, 100)})
    found = " | ".join(run.violations)
    assert "did not finish: SimulationError: hung" in found and "exception escaped a task" in found
    assert "Robot1 tasks: 500, above its bound 100" in found


# --------------------------------------------------------------------------- what really happened


def _take(robot: str, seq: int, obj: str, at_s: float, taken: bool = True) -> Take:
    return Take(robot, 0, seq, obj, at_s, taken, None if taken else "gone")


def test_an_object_taken_off_its_shelf_twice_is_found_across_tasks() -> None:
    """Two tasks of one object, each picked once: the per-task check is
    satisfied, the shelf is not."""
    tasks = [_task(1, "A"), _task(2, "A", "Robot2")]
    picks = [_pick("Robot1", 1, "A"), _pick("Robot2", 2, "A", 2.0)]
    run = _run(tasks, picks, takes=[_take("Robot1", 1, "A", 1.0), _take("Robot2", 2, "A", 2.0)])
    assert any("taken off its shelf twice" in v for v in run.violations), run.violations
    refused = _run(tasks, picks[:1], takes=[_take("Robot1", 1, "A", 1.0), _take("Robot2", 2, "A", 2.0, False)])
    assert not any("shelf" in v for v in refused.violations)


def test_a_take_without_a_majority_s_grant_in_the_lease_is_found() -> None:
    tasks = [_task(1, "A")]
    takes = [_take("Robot1", 1, "A", 10.0)]
    fresh = _run(tasks, [_pick("Robot1", 1, "A", 10.0)], takes=takes, lease_s=3.0,
                 grants=[Grant("Robot2", "Robot1", 8.0)])
    assert fresh.violations == []
    stale = _run(tasks, [_pick("Robot1", 1, "A", 10.0)], takes=takes, lease_s=3.0,
                 grants=[Grant("Robot2", "Robot1", 6.5), Grant("Robot1", "Robot1", 9.0)])
    assert any("grants from 0 of the 1" in v for v in stale.violations), stale.violations


def test_a_take_after_its_task_went_round_again_is_found() -> None:
    tasks = [_task(1, "A", orphaned="Robot1 down"), _task(2, "A", "Robot2", reassigned_from=1)]
    run = _run(tasks, [_pick("Robot1", 1, "A", 9.0)], takes=[_take("Robot1", 1, "A", 9.0)],
               decided_at={(1, 1): 0.5, (1, 2): 6.0})
    assert any("after it went round again as task 2" in v for v in run.violations), run.violations


def test_replicas_unequal_triple_for_triple_or_losing_writes_are_found() -> None:
    insert = WriteOp("w1", "Robot1", "2.04", "Object", "insert", 1, 1.0, 1.2)
    delete = WriteOp("w2", "Robot2", "2.04", "Object", "delete", 1, 3.0, 3.2, settled=True)
    lost = _run([_task(1, "A")], [_pick("Robot1", 1, "A")], writes=[insert],
                values={"Object": {"Robot1": frozenset({1}), "Robot2": frozenset()}})
    assert any("Robot2 lacks acknowledged write w1" in v for v in lost.violations), lost.violations
    back = _run([_task(1, "A")], [_pick("Robot1", 1, "A")], writes=[insert, delete],
                values={"Object": {"Robot1": frozenset({1}), "Robot2": frozenset({1})}})
    assert any("is back on Robot1, Robot2" in v for v in back.violations), back.violations
    split = _run([_task(1, "A")], [_pick("Robot1", 1, "A")], differences={"Object": ["Robot1 and Robot2 differ"]},
                 split_versions=["Robot1 and Robot2 at version 00 of Object show different triples"])
    assert len([v for v in split.violations if "Robot1 and Robot2" in v]) == 2, split.violations


def test_a_write_lost_with_the_last_memory_holding_it_is_excused_with_its_reason() -> None:
    insert = WriteOp("w1", "Robot1", "2.04", "Object", "insert", 1, 1.0, 1.2, copies=2)
    why = "Robot2 was killed at 6.755s with the last copy in memory (no data folder); Robot1 had started 0.251s before"
    lost = _run([_task(1, "A")], [_pick("Robot1", 1, "A")], writes=[insert],
                values={"Object": {"Robot1": frozenset()}}, lost_copies={("Object", 1): why})
    assert not lost.violations
    assert lost.excused == [f"Robot1 lacks acknowledged write w1 (Object value 1, answered Robot1 2.04 at 1.200s): {why}"]


def test_holders_of_other_modules_too_differ_only_where_their_writes_do() -> None:
    """The end of a run compares holders by what changed since their files;
    a holder of two modules and one of one differ in the compared module
    exactly as their whole stores do."""
    cap = "http://www.tcs.org/2018/Capability#"
    files = FilesQuads()
    two = LiveKB(KnowledgeBase.load([ONTOLOGIES / "Capability.owl", ONTOLOGIES / "Location.owl"]), "A.1",
                 wall_ms=wall_ms)
    one = LiveKB(KnowledgeBase.load([ONTOLOGIES / "Capability.owl"]), "B.1", wall_ms=wall_ms)

    def differ() -> set[str]:
        found = files.differ(two, files.changed(two), one, files.changed(one), "Capability")
        # The same, the slow way: every quad of both stores, as quads.
        assert found == of_module(frozenset(two.view.store) ^ frozenset(one.view.store), two, "Capability")
        return {str(q) for q in found}

    for live in (two, one):
        live.update(f'PREFIX : <{cap}> INSERT DATA {{ :Robot1 :note "both" }}')
    assert differ() == set()
    one.update(f'PREFIX : <{cap}> INSERT DATA {{ :Robot2 :note "one" }}')
    two.update(f'PREFIX : <{cap}> DELETE DATA {{ :Robot1 :Robot_Id "Robot1" }}')
    assert differ() == {f'<{cap}Robot2> <{cap}note> "one"', f'<{cap}Robot1> <{cap}Robot_Id> "Robot1"'}


def test_an_exception_a_robot_caught_and_logged_is_a_violation() -> None:
    """A robot that catches what it did not expect keeps running, and its
    teammates may agree on the failed task: no other check sees it (a join
    that raised was found only this way)."""
    caught = "Robot3 at 6.809s: task 7 (A) failed: TypeError: cannot unpack non-iterable NoneType object"
    run = _run([_task(1, "A")], [_pick("Robot1", 1, "A")], exceptions=[caught])
    assert run.violations == [caught]


def test_the_history_keeps_the_exceptions_logged_with_their_traceback_only() -> None:
    history = _History({}, lambda: 1.5, None)

    def record(level: int, message: str, exc: BaseException | None) -> logging.LogRecord:
        return logging.LogRecord("coapkb.agent.controller", level, __file__, 1, message, None,
                                 (type(exc), exc, None) if exc is not None else None)

    history.emit(record(logging.ERROR, "task 7 failed", ValueError("bad")))
    history.emit(record(logging.ERROR, "task 8: no answer", None))  # a fault's error, said without a traceback
    history.emit(record(logging.WARNING, "Robot2 is down", None))
    assert history.exceptions == ["- at 1.500s: task 7 failed: ValueError: bad"]


def test_an_observer_behind_its_robot_once_the_replicas_agree_is_a_violation() -> None:
    behind = ObserverView("observer1", "Robot2", "Object", frozenset({3}), frozenset({3, 13}),
                          ("re-registered: no notification within Max-Age 2 s",))
    caught_up = ObserverView("observer2", "Robot1", "Object", frozenset({3, 13}), frozenset({3, 13}))
    run = _run([_task(1, "A")], [_pick("Robot1", 1, "A")], observers=[behind, caught_up], converged_at=20.0)
    assert len(run.violations) == 1
    assert run.violations[0].startswith("observer1 of Robot2's Object shows {3} while Robot2's KB shows {3, 13}")


def test_an_observer_of_a_robot_that_does_not_run_or_of_replicas_that_never_agreed_is_not_judged() -> None:
    gone = ObserverView("observer1", "Robot2", "Object", frozenset({3}), None)
    run = _run([_task(1, "A")], [_pick("Robot1", 1, "A")], observers=[gone], converged_at=20.0)
    assert run.violations == []
    behind = ObserverView("observer1", "Robot2", "Object", frozenset({3}), frozenset({3, 13}))
    run = _run([_task(1, "A")], [_pick("Robot1", 1, "A")], observers=[behind], converged_at=None)
    assert run.violations == []


def test_an_observation_ended_by_an_error_answer_is_a_violation() -> None:
    ended = ObserverView("observer1", "Robot2", "Object", frozenset({3}), frozenset({3}),
                         ended="answered 5.00 internal error")
    run = _run([_task(1, "A")], [_pick("Robot1", 1, "A")], observers=[ended], converged_at=20.0)
    assert run.violations == ["the observation of observer1 of Robot2's Object ended: Robot2 answered 5.00 "
                              "internal error"]


def test_a_folder_that_restores_less_than_its_robot_held_is_a_violation() -> None:
    lost = "Robot2's data folder restores 4 write ids; it held 5 (1 lost)"
    run = _run([_task(1, "A")], [_pick("Robot1", 1, "A")], restores=[lost])
    assert run.violations == [lost]
