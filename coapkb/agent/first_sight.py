"""What a robot knows of a teammate it has never observed: the process
(``boot``) and the plans heard of elsewhere.  A first state observed that
contradicts them is a restart's, not the process heard of (docs/failover.md,
"Rejoin")."""

from __future__ import annotations

from .robot_state import RobotState


class FirstSight:
    """Per teammate not observed yet: the process and the latest plan heard
    of; both forgotten once a state of it is observed."""

    def __init__(self) -> None:
        #: Robot never observed -> the process (``boot``) its decision as the
        #: leader came from: a first state of another process is a restart's.
        self._boot: dict[str, int] = {}
        #: Robot never observed -> the latest task after which a plan of it
        #: went into a decision here: a first state showing an earlier plan
        #: is another process's.
        self._plan: dict[str, int] = {}

    def forget(self, robot_id: str, boot: int = 0) -> None:
        """Forget what was heard of ``robot_id``; ``boot``: the process now expected (0: any)."""
        self._boot.pop(robot_id, None)
        self._plan.pop(robot_id, None)
        if boot:
            self._boot[robot_id] = boot

    def saw_process(self, robot_id: str, boot: int) -> None:
        self._boot[robot_id] = boot

    def saw_plan(self, robot_id: str, seq: int) -> None:
        self._plan[robot_id] = max(seq, self._plan.get(robot_id, 0))

    def restart(self, robot_id: str, state: RobotState) -> str | None:
        """The first state observed of ``robot_id``: why it is a restart's
        (another process than the one heard of), or None.  Either way what
        was heard is forgotten."""
        seen = self._boot.pop(robot_id, 0)
        planned = self._plan.pop(robot_id, 0)
        if seen and state.boot == seen:
            # The process heard of, showing an older plan: a stale answer (a
            # retransmitted request answered from the exchange cache), not a
            # restart.  Found in the simulator, seed 2118 of the
            # compute-and-communicate swarm profile: a follower cut off while
            # picking took its leader for restarted, and left it out.
            return None
        if state.plan.seq < planned:
            # Never observed before, and earlier than a plan of it already
            # used here: a new process, which decided nothing of that.  Found
            # in the simulator, seed 50486: a robot starved from the start
            # took its teammates' decisions, first observed a teammate after
            # its restart, and waited for its plan of the task before.
            return f"restarted (its plan after task {planned} was used here; it shows task {state.plan.seq})"
        if seen and state.boot and state.boot != seen:
            # Never observed before, but another process of it sent a decision
            # here: this one is a restart.  Found in the simulator: a follower
            # whose observation of its leader was lost took the restarted
            # leader's first state for the old one's, and waited for its
            # decision on a task the new process was never given.  The same
            # for a joiner whose process that took the join died since.
            return "restarted (another process than the one heard of before)"
        return None
