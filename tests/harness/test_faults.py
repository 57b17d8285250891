"""Faults on real processes over real sockets: a small smoke set (a kill, a
freeze, a restart, each on one 3-robot CoAP team) that asserts outcomes and
bounds only hangs.  The fault scenarios themselves, and thousands of seeded
schedules, run in the simulator (tests/sim)."""

from __future__ import annotations

import asyncio

import pytest
from fates import VICTIM, check_fates, check_joined_again
from support import ROOT

from coapkb.agent.observed_states import STATE_PATH
from coapkb.agent.robot_state import RobotState
from coapkb.feeder import TaskRecord
from coapkb.harness.record import TeamRecord
from coapkb.harness.team import Fault, Team, TeamSpec, cluster_modules, draw_tasks
from coapkb.transport import open_client
from coapkb.transport.messages import ContentFormat, Method, Request

ONTOLOGIES = ROOT / "ontologies"


@pytest.mark.slow
async def test_one_robot_killed_mid_run() -> None:
    tasks = draw_tasks(20, ONTOLOGIES, seed=3)
    spec = TeamSpec(robots=3, query_timeout_s=5.0, task_timeout_s=30.0, faults=(Fault("kill", VICTIM, 0.1),))
    async with asyncio.timeout(180):  # a hang detector: one lease request may take task_timeout_s
        async with Team.launch(spec) as team:
            record = await team.run(tasks)
    assert set(record.down) == {VICTIM}
    assert set(record.robot_stats) == set(spec.robot_ids) - {VICTIM}
    [event] = record.faults
    assert (event.action, event.robot) == ("kill", VICTIM)
    assert event.detected_after_s is not None and event.detected_after_s >= 0  # detected; how fast is the faults benchmark's
    check_fates(record, tasks, spec)
    assert TeamRecord.from_dict(record.to_dict()).to_dict() == record.to_dict()


@pytest.mark.slow
@pytest.mark.parametrize(("transport", "discovery"), [("coap", "rd")])
async def test_killed_robot_restarts_and_joins_again(transport: str, discovery: str) -> None:
    # Robot2 is killed while its tasks are queued, started again, and joins
    # at the next task fed: its old tasks go round again, the team takes it
    # back in a new epoch that every robot names, and it works again.  With
    # a directory, the new process finds its teammates there (its
    # configuration lists it alone).
    tasks = draw_tasks(20, ONTOLOGIES, seed=3)
    spec = TeamSpec(
        robots=3, transport=transport, query_timeout_s=5.0, task_timeout_s=30.0, time_scale=20.0,
        faults=(Fault("kill", VICTIM, at_task=3), Fault("restart", VICTIM, at_task=8)), discovery=discovery,
    )
    async with asyncio.timeout(180):  # a hang detector: one lease request may take task_timeout_s
        async with Team.launch(spec) as team:
            record = await team.run(tasks)
    check_joined_again(record, tasks, spec)
    # Scheduled by task, the story is the same on every machine: it joins at task 9.
    assert [t.seq for t in record.tasks if VICTIM in t.joined] == [9]


def test_fault_option_parses_and_is_checked() -> None:
    assert Fault.parse("kill", "Robot4@12s") == Fault("kill", "Robot4", 12.0)
    assert Fault.parse("restart", "Robot4@30") == Fault("restart", "Robot4", 30.0)
    assert Fault.parse("kill", "Robot4@task3") == Fault("kill", "Robot4", at_task=3)
    for bad in ("Robot4", "Robot4@", "@3s", "Robot4@soon", "Robot4@-1s", "Robot4@task0", "Robot4@taskx"):
        with pytest.raises(ValueError, match="ROBOT@"):
            Fault.parse("kill", bad)
    TeamSpec(robots=3, ontologies=ONTOLOGIES, faults=(Fault("kill", "Robot2", at_task=3),
                                                      Fault("restart", "Robot2", at_task=8)))
    with pytest.raises(ValueError, match=r"cannot restart Robot2 at task 8: it is not killed before \(schedule both"):
        TeamSpec(robots=3, ontologies=ONTOLOGIES, faults=(Fault("kill", "Robot2", 1.0),
                                                          Fault("restart", "Robot2", at_task=8)))
    TeamSpec(robots=6, ontologies=ONTOLOGIES, faults=(Fault("kill", "Robot4", 1.0), Fault("restart", "Robot4", 3.0)))
    with pytest.raises(ValueError, match="cannot restart Robot4 at 3s: it is not killed before"):
        TeamSpec(robots=6, ontologies=ONTOLOGIES, faults=(Fault("kill", "Robot4", 4.0), Fault("restart", "Robot4", 3.0)))
    with pytest.raises(ValueError, match="cannot kill Robot7"):
        TeamSpec(robots=6, ontologies=ONTOLOGIES, faults=(Fault("kill", "Robot7", 1.0),))
    assert Fault.parse("stop", "Robot2@1.5s") == Fault("stop", "Robot2", 1.5)
    TeamSpec(robots=3, ontologies=ONTOLOGIES, faults=(Fault("stop", "Robot2", 1.0), Fault("resume", "Robot2", 3.0)))
    with pytest.raises(ValueError, match="cannot resume Robot2 at 3s: it is not stopped before"):
        TeamSpec(robots=3, ontologies=ONTOLOGIES, faults=(Fault("resume", "Robot2", 3.0),))


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


def _pause_case(transport: str) -> tuple[list[str], TeamSpec]:
    """8 tasks for 3 robots, executed at 10x real time: long enough for a
    robot to be stopped and resumed mid-run."""
    tasks = draw_tasks(8, ONTOLOGIES, seed=3)
    return tasks, TeamSpec(robots=3, transport=transport, query_timeout_s=5.0, task_timeout_s=30.0, time_scale=10.0)


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["coap"])
async def test_a_stopped_robot_comes_back_fenced(transport: str) -> None:
    # Robot2 is frozen (SIGSTOP) right after it was given a task, so it holds
    # that job unexecuted; the survivors declare it down, its tasks go round
    # again once its lease has run out, and only then does it go on (SIGCONT),
    # still holding the jobs: it must pick none of them.
    tasks, spec = _pause_case(transport)
    async with asyncio.timeout(180):  # a hang detector: one lease request may take task_timeout_s
        async with Team.launch(spec) as team:
            stopped, resumed = asyncio.Event(), asyncio.Event()

            def progress(record: TaskRecord) -> None:
                if not stopped.is_set() and record.assigned_to == VICTIM:
                    team.pause(VICTIM)
                    stopped.set()
                elif stopped.is_set() and not resumed.is_set() and record.reassigned_from is not None:
                    team.pause(VICTIM, stop=False)  # its tasks are the survivors' now
                    resumed.set()

            async def settled() -> None:
                # The resumed robot has met its fence (or had nothing left to do).
                client = await open_client(transport, security=team.feeder_security())
                request = Request(Method.GET, STATE_PATH, accept=ContentFormat.CBOR)
                try:
                    async for answer in client.observe(team.endpoints[VICTIM], request):
                        live = RobotState.decode(answer.payload).live
                        if live.activity == "idle" and live.queued == 0:
                            return
                finally:
                    await client.aclose()

            record = await team.run(tasks, progress, settled)
    assert stopped.is_set() and resumed.is_set(), [t.fate for t in record.tasks]
    # Down; once back and holding no task, taken back with its own process
    # at the next task, if one was left to join at.
    assert set(record.down) <= {VICTIM}
    assert VICTIM in record.down or any(VICTIM in t.joined for t in record.tasks), record.down
    check_fates(record, tasks, spec)
    # Every task picked exactly once: by the robot it finally went to; the
    # comeback robot dropped the jobs it held, unpicked (a task the others
    # gave it after it froze never reached it).
    victim = record.robot_stats[VICTIM]
    moved = sorted(t.seq for t in record.tasks if t.fate == "reassigned")
    assert victim.fenced and set(victim.fenced) <= set(moved), (victim.fenced, moved)
    assigned = [t for t in record.tasks if t.fate == "assigned"]
    assert sum(s.executed for s in record.robot_stats.values()) == len(assigned)
    assert TeamRecord.from_dict(record.to_dict()).to_dict() == record.to_dict()
