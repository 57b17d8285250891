"""Which tasks go round again: those a robot took and can no longer do."""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence

from ..agent.observed_states import ObservedStates, States
from .record import TaskRecord, claim_of


def idle(states: States, robot_id: str) -> bool:
    state = states.get(robot_id)
    return state is not None and state.live.activity == "idle" and state.live.queued == 0


def unexecuted(
    records: list[TaskRecord], watcher: ObservedStates, robot_id: str, incarnation: Mapping[str, int] | None = None,
    done_before: Mapping[str, int] | None = None,
) -> list[TaskRecord]:
    """The tasks assigned to ``robot_id``'s current process that it has not
    executed (nor dropped), not yet sent round again.  A robot executes its
    jobs in the order assigned, so its last observed ``done`` count, less the
    jobs it had done before these records began (``done_before``), says how
    many of them are finished (a job finished in the instant before a crash
    counts as not done: done again rather than lost).  A task its teammates
    decided late, as skipped because the KB already showed this robot's
    pick of that very task, was its job too, and counts among the done
    (found in the simulator, seed 3619: uncounted, the robot's one done job
    covered its next task, which its dead process never did)."""
    taken = {r.reassigned_from for r in records if r.reassigned_from is not None}
    mine, done = _jobs(records, watcher, robot_id, incarnation, done_before)
    return [r for r in mine[done:] if r.seq not in taken and r.orphaned is None]


def executed_next(
    records: Sequence[TaskRecord], watcher: ObservedStates, robot_id: str, incarnation: Mapping[str, int] | None = None,
    done_before: Mapping[str, int] | None = None,
) -> bool:
    """Whether ``robot_id``'s last observed ``done`` count covers a job past
    every one ``records`` give its current process: the job of a task it
    took that is not among them yet (see :func:`unexecuted`)."""
    mine, done = _jobs(records, watcher, robot_id, incarnation, done_before)
    return done > len(mine)


def _jobs(
    records: Sequence[TaskRecord], watcher: ObservedStates, robot_id: str, incarnation: Mapping[str, int] | None,
    done_before: Mapping[str, int] | None,
) -> tuple[list[TaskRecord], int]:
    """The jobs ``records`` give ``robot_id``'s current process, in the
    order it executes them, and how many of them its last observed state
    says are done."""
    state = watcher.states.get(robot_id)
    done = state.live.done - (done_before or {}).get(robot_id, 0) if state is not None else 0
    fenced = set(state.live.fenced) if state is not None else set()
    first = (incarnation or {}).get(robot_id, 0)
    mine = [r for r in records if (r.assigned_to == robot_id or claim_of(r) == (robot_id, r.seq))
            and r.seq >= first and r.seq not in fenced]
    return mine, done


def orphans(
    records: list[TaskRecord], watcher: ObservedStates, incarnation: Mapping[str, int] | None = None,
    fenced_off: Collection[str] = (),
    only: Collection[str] | None = None,
    done_before: Mapping[str, int] | None = None,
) -> list[TaskRecord]:
    """Tasks to send round again: those a robot now down had not executed
    (only once it is ``fenced_off``: it can no longer pick them), and those a
    robot dropped because it lost its lease.  Only the tasks of a robot's
    last process count: the process before a restart had its own, handled
    when it joined again.  A re-run that is dropped again is not sent round
    a third time: no robot of the cluster could hold a lease for it.
    ``only``: these robots' tasks alone; ``done_before``: see :func:`unexecuted`."""
    taken = {r.reassigned_from for r in records if r.reassigned_from is not None}
    found = []
    for robot_id in fenced_off:
        if robot_id not in watcher.down or (only is not None and robot_id not in only):
            continue
        for record in unexecuted(records, watcher, robot_id, incarnation, done_before):
            record.orphaned = f"{robot_id} went down before executing it: {watcher.down[robot_id]}"
            found.append(record)
    for robot_id, state in watcher.states.items():
        if not state.live.fenced or (only is not None and robot_id not in only):
            continue
        first = (incarnation or {}).get(robot_id, 0)
        for record in records:
            if record.assigned_to != robot_id or record.seq < first or record.seq not in state.live.fenced:
                continue
            if record.seq in taken or record.orphaned is not None or record.unavailable is not None:
                continue
            why = f"{robot_id} dropped it unexecuted: {state.live.fence_reason}"
            if record.reassigned_from is not None:
                record.unavailable = why
                continue
            record.orphaned = why
            found.append(record)
    return sorted(found, key=lambda r: r.seq)
