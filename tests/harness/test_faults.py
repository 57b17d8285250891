"""A robot killed mid-run (SIGKILL, real processes on loopback): the survivors
declare it down, agree on the new membership, re-assign what it had not done,
and the run ends by itself with every task's fate recorded exactly once."""

from __future__ import annotations

import asyncio

import pytest

from coapkb.harness.record import TeamRecord
from coapkb.harness.team import Fault, Team, TeamSpec, cluster_modules, draw_tasks, split_tasks

from support import ROOT

ONTOLOGIES = ROOT / "ontologies"
VICTIM = "Robot2"


def check_fates(
    record: TeamRecord, tasks: list[str], spec: TeamSpec, victims: frozenset[str] = frozenset({VICTIM}),
    fates: tuple[str, ...] = ("assigned", "skipped", "reassigned"),
    new_epoch: bool = True,
) -> None:
    """Every task given has one final fate; a re-assigned task names the task it
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
    after = [t for t in record.tasks if t.epochs and max(t.epochs.values()) > 0]
    assert after or not new_epoch, "no decision named the membership without the dead robot"
    for task in after:
        # (A victim may still be a member if it died after this decision.)
        excluded = [v for v in victims if v not in task.members]
        assert excluded and all(v in task.absent for v in excluded), task
        assert task.assigned_to not in excluded, task
    # Each survivor executed exactly the tasks finally assigned to it: none twice.
    final = [t for t in record.tasks if t.fate == "assigned"]
    for robot_id, stats in record.robot_stats.items():
        assert stats.executed == sum(t.assigned_to == robot_id for t in final), robot_id


@pytest.mark.slow
@pytest.mark.parametrize(("transport", "robots"), [("coap", 6), ("zmq", 6), ("coap", 9), ("zmq", 9)])
async def test_one_robot_killed_mid_run(transport: str, robots: int) -> None:
    tasks = draw_tasks(40, ONTOLOGIES, seed=3)
    spec = TeamSpec(
        robots=robots, transport=transport, query_timeout_s=5.0, task_timeout_s=30.0,
        faults=(Fault("kill", VICTIM, 0.1),),
    )
    async with asyncio.timeout(40):
        async with Team.launch(spec) as team:
            record = await team.run(tasks)
    assert set(record.down) == {VICTIM}
    assert set(record.robot_stats) == set(spec.robot_ids) - {VICTIM}
    [event] = record.faults
    assert (event.action, event.robot) == ("kill", VICTIM)
    assert event.detected_after_s is not None and 0 <= event.detected_after_s < 15
    check_fates(record, tasks, spec)
    assert TeamRecord.from_dict(record.to_dict()).to_dict() == record.to_dict()


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["coap", "zmq"])
async def test_both_holders_of_a_module_killed(transport: str) -> None:
    # Robot1 and Robot2 hold the Object KB (replication 2 of three): the
    # survivor says which tasks need it and why, and does the others.
    tasks = draw_tasks(8, ONTOLOGIES, seed=3)
    victims = frozenset({"Robot1", "Robot2"})
    spec = TeamSpec(
        robots=3, transport=transport, query_timeout_s=5.0, task_timeout_s=30.0,
        faults=tuple(Fault("kill", v, 0.3) for v in sorted(victims)),
    )
    async with asyncio.timeout(60):
        async with Team.launch(spec) as team:
            record = await team.run(tasks)
    assert set(record.down) == victims
    # Tasks that fail for want of the module are decided before any plan
    # changes the membership: no new epoch need appear.
    check_fates(record, tasks, spec, victims, ("assigned", "skipped", "reassigned", "unavailable", "unassigned"),
                new_epoch=False)
    unavailable = [t for t in record.tasks if t.fate == "unavailable"]
    assert unavailable, [t.fate for t in record.tasks]
    for task in unavailable:
        assert task.unavailable is not None and "no live robot holds the Object KB" in task.unavailable, task
        assert task.assigned_to is None
    assert TeamRecord.from_dict(record.to_dict()).to_dict() == record.to_dict()


def test_fault_option_parses_and_is_checked() -> None:
    assert Fault.parse("kill", "Robot4@12s") == Fault("kill", "Robot4", 12.0)
    assert Fault.parse("restart", "Robot4@30") == Fault("restart", "Robot4", 30.0)
    for bad in ("Robot4", "Robot4@", "@3s", "Robot4@soon", "Robot4@-1s"):
        with pytest.raises(ValueError, match="ROBOT@SECONDS"):
            Fault.parse("kill", bad)
    with pytest.raises(ValueError, match="cannot restart Robot4: a restarted robot cannot rejoin"):
        TeamSpec(robots=6, ontologies=ONTOLOGIES, faults=(Fault("kill", "Robot4", 1.0), Fault("restart", "Robot4", 3.0)))
    with pytest.raises(ValueError, match="cannot kill Robot7"):
        TeamSpec(robots=6, ontologies=ONTOLOGIES, faults=(Fault("kill", "Robot7", 1.0),))


def test_replication_puts_every_module_on_r_robots_of_a_cluster() -> None:
    for replication in (1, 2, 3):
        spec = TeamSpec(ontologies=ONTOLOGIES, replication=replication)
        held = [cluster_modules(i, spec) for i in range(3)]
        assert all(len(m) == replication for m in held)
        for module in ("Location", "Object", "Capability"):
            assert sum(module in m for m in held) == replication
    assert cluster_modules(0, TeamSpec(ontologies=ONTOLOGIES, replication=1)) == ("Location",)
    with pytest.raises(ValueError, match="replication"):
        TeamSpec(ontologies=ONTOLOGIES, replication=4)
