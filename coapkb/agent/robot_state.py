"""A robot's state, as its teammates see it through ``/robot/state`` (Observe).

Two parts with different jobs:

* ``plan``: the state the Task Assigner reasons with (where the robot will be,
  its battery and load once its assigned tasks are done) and ``seq``, the last
  task it has decided.  It changes only at decisions, so every robot that
  waits for its teammates' ``seq`` computes on identical inputs, which is what
  makes "compute by all" agree.
* ``live``: what the robot is doing now (the Task Executor's progress), for
  people and monitors; never used for decisions.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Any

import cbor2


@dataclass(frozen=True)
class PlannedState:
    aisle: int
    rack: int
    battery_wh: float
    load_kg: float
    payload_kg: float
    #: Sequence number of the last task this robot has decided (0 = none yet).
    seq: int = 0


@dataclass(frozen=True)
class Decision:
    """One robot's outcome for one task."""

    seq: int
    object: str
    skipped: bool = False
    assigned_to: str | None = None
    #: Cost in Wh per robot; None for robots that cannot take the task.
    costs: dict[str, float | None] = field(default_factory=dict)
    error: str | None = None
    coordination_s: float = 0.0


@dataclass(frozen=True)
class LiveState:
    aisle: float
    rack: float
    activity: str = "idle"  # idle | travelling | picking | unloading
    executing: str | None = None
    queued: int = 0
    done: int = 0


@dataclass(frozen=True)
class RobotState:
    robot_id: str
    plan: PlannedState
    live: LiveState
    last: Decision | None = None
    #: The plan before the last decision: a teammate that is one task ahead
    #: still shows the state the others need for that task.
    prev: PlannedState | None = None

    def with_plan(self, plan: PlannedState, last: Decision) -> "RobotState":
        return replace(self, plan=plan, last=last, prev=self.plan)

    def plan_at(self, seq: int) -> PlannedState | None:
        """The planned state right after task ``seq`` was decided, if still known."""
        for plan in (self.plan, self.prev):
            if plan is not None and plan.seq == seq:
                return plan
        return None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def encode(self) -> bytes:
        return cbor2.dumps(self.to_dict())

    @classmethod
    def decode(cls, data: bytes) -> "RobotState":
        try:
            raw = cbor2.loads(data)
            last, prev = raw.get("last"), raw.get("prev")
            return cls(
                robot_id=raw["robot_id"],
                plan=PlannedState(**raw["plan"]),
                live=LiveState(**raw["live"]),
                last=Decision(**last) if last else None,
                prev=PlannedState(**prev) if prev else None,
            )
        except (cbor2.CBORDecodeError, KeyError, TypeError, AttributeError) as exc:
            raise ValueError(f"not a robot state: {exc}") from None
