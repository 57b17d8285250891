"""What the feeder saw of one task: every robot's decision on it.

:meth:`TaskRecord.to_dict` is the per-task entry of ``coapkb team
--record``'s JSON; :meth:`TaskRecord.from_dict` reads one back.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping


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

    @property
    def agreed(self) -> bool:
        """Every robot that decided took the same decision in the same
        membership epoch, and none failed."""
        return len(set(self.decisions.values())) == 1 and not self.errors and len(set(self.epochs.values())) <= 1

    @property
    def fate(self) -> str:
        """One word: skipped, assigned, reassigned (went round again as a later
        task), failed (errors or disagreement), unavailable (a KB module it
        needs had no live holder) or unassigned (nobody could)."""
        if self.skipped:
            return "skipped"
        if not self.agreed:
            return "failed"
        if self.unavailable is not None:
            return "unavailable"
        if self.orphaned is not None:
            return "reassigned"
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
            "fate": self.fate,  # derived, like "agreed"
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "TaskRecord":
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
        )
