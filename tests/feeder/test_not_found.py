"""The fate not-found and every skip's reason in the feeder's record: which
task a robot's ``missed`` names (mark_not_found), the kinds of skip reason,
the counts and their summary line, and the record's JSON."""

from __future__ import annotations

import json
from dataclasses import replace

from coapkb.agent.robot_state import LiveState, PlannedState, RobotState
from coapkb.feeder import FateCounts, TaskRecord
from coapkb.feeder.record import by_assignment, claim_of, mark_not_found, skip_kind, unclaim
from coapkb.harness.record import TeamRecord, summarise
from coapkb.transport.base import TrafficCounters

MISPLACED = "not where the KB says it is (misplaced)"
DECIDED = {"Robot1": "Robot1", "Robot2": "Robot1", "Robot3": "Robot1"}


def _state(robot_id: str, *missed: tuple[int, str]) -> RobotState:
    return RobotState(robot_id, PlannedState(1, 0, 400.0, 0.0, 60.0, 9), LiveState(1.0, 0.0, missed=tuple(missed)))


def _assigned(seq: int, robot: str = "Robot1", obj: str = "Barilla_pasta_1") -> TaskRecord:
    return TaskRecord(obj, 1, seq, assigned_to=robot, decisions={r: robot for r in DECIDED})


def _skipped(seq: int, reason: str | None, obj: str = "Gucci_bag_14") -> TaskRecord:
    return TaskRecord(obj, 1, seq, skipped=True, decisions={r: None for r in DECIDED}, skip_reason=reason)


def test_skip_kinds() -> None:
    assert skip_kind(None) == "no such object"  # a record from before skip reasons
    assert skip_kind("no such object") == "no such object"
    assert skip_kind("picked by Robot2 at task 1") == "already picked"
    assert skip_kind("missing from its place since task 4") == "missing"


def test_a_robots_missed_task_marks_its_record_not_found() -> None:
    four, five = _assigned(4), _assigned(5, robot="Robot2", obj="Canon_tv_538")
    records = [_skipped(3, "picked by Robot2 at task 1"), four, five]
    mark_not_found(by_assignment(records), {"Robot1": _state("Robot1", (4, MISPLACED)), "Robot2": _state("Robot2"),
                             "Robot3": _state("Robot3")})
    assert four.not_found == f"Robot1 did not find it: {MISPLACED}"
    assert (four.fate, five.fate, records[0].fate) == ("not-found", "assigned", "skipped")
    assert five.not_found is None


def test_a_missed_task_names_only_the_robot_it_went_to() -> None:
    """Robot2 says it missed task 4, but task 4 went to Robot1: a mix-up, not Robot1's miss."""
    four = _assigned(4)
    mark_not_found(by_assignment([four]), {"Robot2": _state("Robot2", (4, MISPLACED))})
    assert four.not_found is None and four.fate == "assigned"


def test_the_first_reason_stands_and_old_tasks_are_ignored() -> None:
    four = _assigned(4)
    mark_not_found(by_assignment([four]), {"Robot1": _state("Robot1", (4, MISPLACED))})
    # Read again after the next decision, with a task the records do not hold.
    mark_not_found(by_assignment([four]), {"Robot1": _state("Robot1", (2, "gone: picked by Robot4 at task 1"),
                                                      (4, "gone: picked by Robot4 at task 3"))})
    assert four.not_found == f"Robot1 did not find it: {MISPLACED}"


def test_a_reassigned_task_is_reassigned_though_its_robot_missed_it() -> None:
    four = replace(_assigned(4), orphaned="Robot1 went down before executing it")
    mark_not_found(by_assignment([four]), {"Robot1": _state("Robot1", (4, MISPLACED))})
    assert four.fate == "reassigned"


def test_the_counts_split_skips_by_kind_and_count_not_found_once() -> None:
    tasks = [
        _assigned(1, obj="Gucci_bag_14"),
        _assigned(2, robot="Robot2", obj="Canon_tv_538"),
        _skipped(3, "picked by Robot1 at task 1"),
        replace(_assigned(4), not_found=f"Robot1 did not find it: {MISPLACED}"),
        _skipped(5, "picked by Robot2 at task 2", obj="Canon_tv_538"),
        _skipped(6, "missing from its place since task 4", obj="Barilla_pasta_1"),
        _skipped(7, "no such object", obj="Nonexistent_thing_1"),
        _skipped(8, None, obj="Nonexistent_thing_2"),
    ]
    counts = FateCounts.of(tasks)
    assert (counts.assigned, counts.skipped, counts.not_found) == (2, 5, 1)
    assert counts.skip_kinds == {"already picked": 2, "no such object": 2, "missing": 1}
    assert counts.counted == counts.tasks == len(tasks)
    assert counts.line() == ("8 tasks, 2 assigned, 5 skipped (2 already picked, 2 no such object, 1 missing), "
                             "0 unassigned, 0 unavailable, 0 reassigned, 1 not found, 0 with errors, "
                             "0 disagreements")


def test_no_skips_no_kinds() -> None:
    counts = FateCounts.of([_assigned(1)])
    assert counts.skip_kinds == {} and "1 assigned, 0 skipped, 0 unassigned" in counts.line()


def test_skip_reasons_and_not_found_survive_the_records_json() -> None:
    tasks = [_skipped(3, "picked by Robot2 at task 1"),
             replace(_assigned(4), not_found=f"Robot1 did not find it: {MISPLACED}")]
    for task in tasks:
        data = json.loads(json.dumps(task.to_dict()))
        assert TaskRecord.from_dict(data) == task
        assert TaskRecord.from_dict(data).to_dict() == data
    assert tasks[0].to_dict()["skip_reason"] == "picked by Robot2 at task 1"
    assert tasks[1].to_dict()["fate"] == "not-found"
    assert tasks[1].to_dict()["not_found"] == f"Robot1 did not find it: {MISPLACED}"
    # A record from before either: neither is named.
    old = {k: v for k, v in tasks[1].to_dict().items() if k not in ("skip_reason", "not_found")}
    back = TaskRecord.from_dict(old)
    assert (back.skip_reason, back.not_found, back.fate) == (None, None, "assigned")


def test_the_summary_names_each_task_not_found() -> None:
    tasks = [
        _assigned(1, obj="Gucci_bag_14"),
        _skipped(2, "picked by Robot1 at task 1"),
        replace(_assigned(3), not_found=f"Robot1 did not find it: {MISPLACED}"),
    ]
    record = TeamRecord(
        mode="distributed", transport="coap", strategy="compute-by-all", query_wire="compact",
        robots=["Robot1", "Robot2", "Robot3"], clusters=[["Robot1", "Robot2", "Robot3"]], tasks=tasks,
        coordination_s=0.5, completion_s=1.0, robot_stats={}, feeder_traffic=TrafficCounters(),
    )
    lines = summarise(record).splitlines()
    assert lines[0] == ("3 robots, distributed, coap, compute-by-all: 3 tasks, 1 assigned, 1 skipped "
                        "(1 already picked), 0 unassigned, 0 unavailable, 0 reassigned, 1 not found, "
                        "0 with errors, 0 disagreements")
    assert lines[1] == "assigned: Robot1 1"  # the task not found is not counted as done
    assert lines[-1] == f"not found: task 3 Barilla_pasta_1 (cluster 1): Robot1 did not find it: {MISPLACED}"
    data = json.loads(json.dumps(record.to_dict()))
    assert data["fates"]["not_found"] == 1 and data["fates"]["skip_kinds"] == {"already picked": 1}
    assert TeamRecord.from_dict(data).to_dict() == data


def test_a_skip_on_a_claim_whose_robot_found_the_shelf_empty_says_missing() -> None:
    """The robots skip a repeat on the cluster's claim ("picked by Robot1 at
    task 4") before the robot reaches the shelf; once it reports the object
    not there, the record says it is missing and counts it so."""
    four, six = _assigned(4), _skipped(6, "picked by Robot1 at task 4", obj="Barilla_pasta_1")
    assert claim_of(six) == ("Robot1", 4)
    assert claim_of(_skipped(7, "missing from its place since task 4")) is None
    assert claim_of(_skipped(8, "no such object")) is None
    assigned = by_assignment([four, six])
    [marked] = mark_not_found(assigned, {"Robot1": _state("Robot1", (4, MISPLACED))})
    assert marked is four
    assert mark_not_found(assigned, {"Robot1": _state("Robot1", (4, MISPLACED))}) == []  # marked once
    unclaim(six, four)
    assert six.skip_reason == "missing from its place since task 4"
    assert FateCounts.of([four, six]).skip_kinds == {"missing": 1}


def test_a_skip_on_a_claim_another_cluster_won_names_the_pick() -> None:
    four = _assigned(4)
    four.not_found = "Robot1 did not find it: gone: picked by Robot5 at task 2"
    six = _skipped(6, "picked by Robot1 at task 4", obj="Barilla_pasta_1")
    unclaim(six, four)
    assert six.skip_reason == "picked by Robot5 at task 2"
    assert skip_kind(six.skip_reason) == "already picked"
