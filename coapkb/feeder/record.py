"""What the feeder saw of one task: every robot's decision on it.

:meth:`TaskRecord.to_dict` is the per-task entry of ``coapkb team
--record``'s JSON; :meth:`TaskRecord.from_dict` reads one back.
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any


@dataclass
class TaskRecord:
    """One task as the feeder saw it: what every robot of its cluster decided."""

    object: str
    cluster: int
    seq: int
    skipped: bool = False
    assigned_to: str | None = None
    decisions: dict[str, str | None] = field(default_factory=dict)
    costs: dict[str, float | None] = field(default_factory=dict)
    reasons: dict[str, str] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)
    coordination_s: float = 0.0
    #: Robots of the cluster that were down and did not decide: robot -> why.
    absent: dict[str, str] = field(default_factory=dict)
    #: The membership epoch each deciding robot named, and the members it named.
    epochs: dict[str, int] = field(default_factory=dict)
    members: list[str] = field(default_factory=list)
    #: This task is a re-run of task ``reassigned_from`` of the same cluster.
    reassigned_from: int | None = None
    #: Why this task went round again (its robot went down before executing it).
    orphaned: str | None = None
    #: Why the team could not do this task: a KB module it needs had no live holder.
    unavailable: str | None = None
    #: Robots (restarted) that joined the team again at this task.
    joined: list[str] = field(default_factory=list)
    #: Why nobody picks it: no such object, picked (by whom, at which task), missing.
    skip_reason: str | None = None
    #: The robot it went to did not find the object at the shelf: who, and why.
    not_found: str | None = None

    @property
    def agreed(self) -> bool:
        """Every robot that decided took the same decision in the same
        membership epoch, and none failed."""
        return len(set(self.decisions.values())) == 1 and not self.errors and len(set(self.epochs.values())) <= 1

    @property
    def fate(self) -> str:
        """One word: skipped, assigned, reassigned (went round again as a later
        task), failed (errors or disagreement), unavailable (a KB module it
        needs had no live holder), not-found (its robot did not find the
        object at the shelf) or unassigned (nobody could)."""
        if self.skipped:
            return "skipped"
        if self.orphaned is not None and not self.decisions:
            return "reassigned"  # nobody decided it: it went round again
        if not self.agreed:
            return "failed"
        if self.unavailable is not None:
            return "unavailable"
        if self.orphaned is not None:
            return "reassigned"
        if self.not_found is not None:
            return "not-found"
        return "assigned" if self.assigned_to else "unassigned"

    def to_dict(self) -> dict[str, Any]:
        return {
            "object": self.object,
            "cluster": self.cluster,
            "seq": self.seq,
            "skipped": self.skipped,
            "assigned_to": self.assigned_to,
            "decisions": self.decisions,
            "costs": self.costs,
            "reasons": self.reasons,
            "errors": self.errors,
            "agreed": self.agreed,  # derived; written for readers of the JSON, ignored on reading
            "coordination_s": round(self.coordination_s, 6),
            "absent": self.absent,
            "epochs": self.epochs,
            "members": self.members,
            "reassigned_from": self.reassigned_from,
            "orphaned": self.orphaned,
            "unavailable": self.unavailable,
            "joined": self.joined,
            "skip_reason": self.skip_reason,
            "not_found": self.not_found,
            "fate": self.fate,  # derived, like "agreed"
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> TaskRecord:
        return cls(
            object=str(data["object"]),
            cluster=int(data["cluster"]),
            seq=int(data["seq"]),
            skipped=bool(data.get("skipped", False)),
            assigned_to=data.get("assigned_to"),
            decisions=dict(data.get("decisions") or {}),
            costs=dict(data.get("costs") or {}),
            reasons=dict(data.get("reasons") or {}),
            errors=dict(data.get("errors") or {}),
            coordination_s=float(data.get("coordination_s", 0.0)),
            absent=dict(data.get("absent") or {}),
            epochs={str(r): int(e) for r, e in (data.get("epochs") or {}).items()},
            members=[str(r) for r in data.get("members") or ()],
            reassigned_from=data.get("reassigned_from"),
            orphaned=data.get("orphaned"),
            unavailable=data.get("unavailable"),
            joined=[str(r) for r in data.get("joined") or ()],
            skip_reason=data.get("skip_reason"),
            not_found=data.get("not_found"),
        )


def skip_kind(reason: str | None) -> str:
    """The kind of a skip reason: "no such object", "already picked" or "missing"."""
    if reason is None or reason == "no such object":
        return "no such object"
    if reason.startswith("picked by"):
        return "already picked"
    return "missing"


def by_assignment(records: Sequence[TaskRecord]) -> dict[tuple[str, int], TaskRecord]:
    """(robot, task) -> the record of each task given to a robot."""
    return {(r.assigned_to, r.seq): r for r in records if r.assigned_to is not None}


def mark_not_found(
    assigned: Mapping[tuple[str, int], TaskRecord], states: Mapping[str, Any]
) -> list[TaskRecord]:
    """Mark the tasks whose robot did not find the object at the shelf, as its
    live state names them (``missed``: the latest few); ``assigned``: see
    :func:`by_assignment` (kept up as tasks are decided, so a shift of
    thousands of tasks is not indexed again after each one).  Returns the
    records marked now."""
    marked = []
    for robot_id, state in states.items():
        for seq, why in state.live.missed:
            record = assigned.get((robot_id, seq))
            if record is not None and record.not_found is None:
                record.not_found = f"{robot_id} did not find it: {why}"
                marked.append(record)
    return marked


_CLAIM = re.compile(r"picked by (\S+) at task (\d+)")


def claim_of(record: TaskRecord) -> tuple[str, int] | None:
    """(robot, task) a skip names as the object's pick ("picked by Robot2 at
    task 1"), or None."""
    match = _CLAIM.fullmatch(record.skip_reason or "") if record.skipped else None
    return (match.group(1), int(match.group(2))) if match else None


def unclaim(skip: TaskRecord, claimed: TaskRecord) -> None:
    """A skip that named the pick of task ``claimed`` when that task's robot
    then did not find the object: the robots skipped on the cluster's claim,
    before anyone went to the shelf, but nobody picked it.  The record says
    what became of the object instead: missing from its place since that
    task, or picked by whoever took it first (another cluster)."""
    why = (claimed.not_found or "").split(": ", 1)[-1]
    skip.skip_reason = (why.removeprefix("gone: ") if why.startswith("gone: picked by ")
                        else f"missing from its place since task {claimed.seq}")


@dataclass(frozen=True)
class FateCounts:
    """How many tasks met each fate: every task counted once, so the counts
    add up to ``tasks``.  A failed task is counted as ``errors`` when a robot
    failed on it, else as a ``disagreement``.  ``coapkb team``, ``coapkb
    feed`` and ``coapkb bench`` print :meth:`line`."""

    tasks: int = 0
    assigned: int = 0
    skipped: int = 0
    unassigned: int = 0
    unavailable: int = 0
    reassigned: int = 0
    not_found: int = 0
    errors: int = 0
    disagreements: int = 0
    #: Why nobody took the unassigned tasks: the robots' commonest reason, and on how many tasks.
    unassigned_reason: str | None = None
    unassigned_reason_tasks: int = 0
    #: Skipped tasks by kind of reason: no such object, already picked, missing.
    skip_kinds: dict[str, int] = field(default_factory=dict)

    @classmethod
    def of(cls, tasks: Sequence[TaskRecord]) -> FateCounts:
        fates = Counter(t.fate for t in tasks)
        failed = [t for t in tasks if t.fate == "failed"]
        errors = sum(1 for t in failed if t.errors)
        # Each unassigned task's own commonest reason (its robots may differ:
        # one cannot pick by suction, another's battery is low), then the
        # commonest of those over the tasks.
        reasons = Counter(
            Counter(t.reasons.values()).most_common(1)[0][0]
            for t in tasks if t.fate == "unassigned" and t.reasons
        )
        reason, reason_tasks = reasons.most_common(1)[0] if reasons else (None, 0)
        return cls(
            tasks=len(tasks), assigned=fates["assigned"], skipped=fates["skipped"],
            unassigned=fates["unassigned"], unavailable=fates["unavailable"], reassigned=fates["reassigned"],
            not_found=fates["not-found"], errors=errors, disagreements=len(failed) - errors,
            unassigned_reason=reason, unassigned_reason_tasks=reason_tasks,
            skip_kinds=dict(Counter(skip_kind(t.skip_reason) for t in tasks if t.fate == "skipped").most_common()),
        )

    @property
    def counted(self) -> int:
        """The sum of the fates' counts: equal to ``tasks``."""
        return (self.assigned + self.skipped + self.unassigned + self.unavailable + self.reassigned
                + self.not_found + self.errors + self.disagreements)

    def line(self) -> str:
        """``60 tasks, 18 assigned, 0 skipped, 42 unassigned, ...`` and, if
        any went unassigned, the robots' commonest reason."""
        skipped = f"{self.skipped} skipped"
        if self.skip_kinds:
            skipped += " (" + ", ".join(f"{n} {kind}" for kind, n in self.skip_kinds.items()) + ")"
        text = (f"{self.tasks} tasks, {self.assigned} assigned, {skipped}, "
                f"{self.unassigned} unassigned, {self.unavailable} unavailable, {self.reassigned} reassigned, "
                f"{self.not_found} not found, {self.errors} with errors, {self.disagreements} disagreements")
        if self.unassigned_reason is not None:
            text += (f"; unassigned mostly as {self.unassigned_reason!r} "
                     f"({self.unassigned_reason_tasks} of {self.unassigned} tasks)")
        return text
