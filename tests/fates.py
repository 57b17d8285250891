"""What every run with faults must show in its record, simulated or real:
the check the fault tests share."""

from __future__ import annotations

from coapkb.feeder import split_tasks
from coapkb.harness.record import TeamRecord
from coapkb.harness.team import TeamSpec

VICTIM = "Robot2"


def check_fates(
    record: TeamRecord, tasks: list[str], spec: TeamSpec, victims: frozenset[str] = frozenset({VICTIM}),
    fates: tuple[str, ...] = ("assigned", "skipped", "reassigned", "not-found"),
    new_epoch: bool = True,
) -> None:
    """Every task given has one final fate (an object drawn twice may be
    picked by another cluster first: not found); a re-assigned task names the task it
    replaces, which names why; survivors decided alike, in the same epoch."""
    for index, share in enumerate(split_tasks(tasks, len(spec.clusters()))):
        cluster = [t for t in record.tasks if t.cluster == index + 1]
        originals = [t for t in cluster if t.reassigned_from is None]
        assert [t.object for t in originals] == share
        assert [t.seq for t in cluster] == list(range(1, len(cluster) + 1))
        by_seq = {t.seq: t for t in cluster}
        reruns = [t for t in cluster if t.reassigned_from is not None]
        assert len({t.reassigned_from for t in reruns}) == len(reruns), "a task went round twice"
        for rerun in reruns:
            original = by_seq[rerun.reassigned_from]  # type: ignore[index]
            assert original.object == rerun.object and original.fate == "reassigned", original
            assert original.orphaned and any(v in original.orphaned for v in victims)
        for task in cluster:
            assert task.fate in fates, task
            assert task.agreed, task
            if task.fate == "reassigned":
                assert task.seq in {t.reassigned_from for t in reruns}, task
    # Survivors never pick the dead robot once they excluded it, and name the new epoch.
    # (A victim may still be a member if it died after the decision, or again
    # once it joined after a restart.)
    after = [t for t in record.tasks if t.epochs and max(t.epochs.values()) > 0]
    without = [t for t in after if any(v not in t.members for v in victims)]
    assert without or not new_epoch, "no decision named the membership without the dead robot"
    for task in without:
        excluded = [v for v in victims if v not in task.members]
        assert all(v in task.absent for v in excluded), task
        assert task.assigned_to not in excluded, task
    # Each survivor executed exactly the tasks finally assigned to it: none
    # twice (a robot that joined again: its new process, from its join on).
    # A task whose object it did not find counts: it went there.
    final = [t for t in record.tasks if t.fate in ("assigned", "not-found")]
    joined_at = {r: t.seq for t in record.tasks for r in t.joined}
    for robot_id, stats in record.robot_stats.items():
        mine = [t for t in final if t.assigned_to == robot_id and t.seq >= joined_at.get(robot_id, 0)]
        assert stats.executed == len(mine), robot_id


def check_joined_again(record: TeamRecord, tasks: list[str], spec: TeamSpec) -> None:
    """Robot2 was killed and restarted: it joined at one task, every robot
    names one epoch from then on (a new one if the membership had left it
    out before its join), it got work again, and every task has one fate."""
    assert [(e.action, e.robot) for e in record.faults] == [("kill", VICTIM), ("restart", VICTIM)]
    [join] = [t for t in record.tasks if t.joined]
    assert join.joined == [VICTIM]
    check_fates(record, tasks, spec, new_epoch=False)
    earlier = [t for t in record.tasks if t.seq < join.seq]
    before = max((t.epochs.get("Robot1", 0) for t in earlier), default=0)
    last = max(earlier, key=lambda t: t.seq, default=None)
    left_out = last is not None and bool(last.members) and VICTIM not in last.members
    for task in record.tasks:
        if task.seq >= join.seq:
            assert set(task.members) == {"Robot1", "Robot2", "Robot3"} and not task.absent, task
            assert set(task.epochs) == {"Robot1", "Robot2", "Robot3"}, task
            assert set(task.epochs.values()) == {before + left_out}, task
    assert any(t.assigned_to == VICTIM for t in record.tasks if t.seq >= join.seq), "the new Robot2 got no task"
    assert set(record.robot_stats) == set(spec.robot_ids) and not record.down
