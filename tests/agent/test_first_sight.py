"""What a robot knows of a teammate it has never observed decides whether
the first state observed of it is a restart's."""

from __future__ import annotations

from coapkb.agent.first_sight import FirstSight
from coapkb.agent.robot_state import LiveState, PlannedState, RobotState


def _state(seq: int, boot: int) -> RobotState:
    return RobotState("Robot1", PlannedState(1, 0, 400.0, 0.0, 40.0, seq=seq), LiveState(1.0, 0.0), boot=boot)


def test_an_older_plan_of_the_process_heard_of_is_a_stale_answer_not_a_restart() -> None:
    """Process 7 of Robot1 sent its decisions here as the leader, and its plan
    after task 1 was used; a first state of process 7 showing task 0 is an
    old answer (a retransmitted request answered from the exchange cache),
    not a restart (simulator, the compute-and-communicate swarm profile,
    seeds 1045 and 2118: a follower cut off while picking left its leader
    out)."""
    sight = FirstSight()
    sight.saw_process("Robot1", 7)
    sight.saw_plan("Robot1", 1)
    assert sight.restart("Robot1", _state(0, boot=7)) is None


def test_an_older_plan_or_another_process_is_a_restart() -> None:
    sight = FirstSight()
    sight.saw_plan("Robot1", 1)  # no process heard of: the plan says it (seed 50486)
    assert "restarted" in (sight.restart("Robot1", _state(0, boot=9)) or "")
    sight.saw_process("Robot1", 7)
    assert "another process" in (sight.restart("Robot1", _state(3, boot=9)) or "")
    sight.saw_process("Robot1", 7)
    assert sight.restart("Robot1", _state(3, boot=7)) is None
